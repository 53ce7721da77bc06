"""The run on disk: its directory, checkpoints, the replay's block files, logs, counters and saved state."""
