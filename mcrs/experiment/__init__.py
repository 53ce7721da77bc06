"""Experiments: validated configs, the training loop, evaluation, checkpoints and logging."""
