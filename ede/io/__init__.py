"""What is on disk and whether it is whole: rollouts, atomic writes, locks and provenance."""
