"""A run stepping, stopping and resuming: the code executor, the environments, training,
checkpoints, artifacts and run folders."""
