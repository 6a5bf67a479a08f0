"""What the runs say: statistics, the results model, probes, figures and video."""
