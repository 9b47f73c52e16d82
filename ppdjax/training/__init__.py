"""Training: the train state, the loader, the loop, checkpoints and data parallelism."""
