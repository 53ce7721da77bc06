"""Experiments: the config, the training loop, the run on disk and the command lines.

Rooms, bottom to top (tests/test_layering.py keeps the order):

- ``util``: small helpers that know nothing of a run: atomic writes, untrusted text, tables, thread counts,
  one-line messages.
- ``schema`` and ``config`` (modules here): the typed config and the checks of its values.
- ``run``: the run on disk: its directory, checkpoints, the replay's files, logs, counters and the state
  a checkpoint holds (``RunState``).
- ``training``: the loop: ``Experiment``, the learner, algorithms, callbacks, episodic memory, tasks,
  collection, replay and evaluation.
- ``commands``: the command lines' Hydra glue: one-line errors, the run directory check, sweeps, the log
  format.

``training`` and ``commands`` stand side by side: neither imports the other.
"""
