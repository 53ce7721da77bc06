"""Experiments: the config, the training loop, the run on disk and the command lines.

Rooms, bottom to top (tests/test_layering.py keeps the order):

- ``util``: small helpers that know nothing of a run.
- ``schema`` and ``config`` (modules here): the typed config and the checks of its values.
- ``run``: the run on disk: its directory, checkpoints, replay files, logs and saved state.
- ``training``: the loop: ``Experiment`` and the parts it builds.
- ``commands``: the command lines' Hydra glue. It and ``training`` never import each other.
"""
