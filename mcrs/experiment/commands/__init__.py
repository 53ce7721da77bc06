"""The command lines' Hydra glue: one-line errors, the run directory check, sweep progress, the log format."""
