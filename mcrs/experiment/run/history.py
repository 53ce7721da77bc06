"""What older forms mean: the compatibility rules for checkpoints and records written by earlier versions.

Each rule says what the old form meant, so that the code that reads it need not.
"""

from __future__ import annotations

#: The rooms of :mod:`mcrs.experiment`. Its modules were once all at the top (``mcrs.experiment.trainer``).
ROOMS = ("util", "run", "training", "commands")

#: ``last_eval_step`` of a checkpoint written before that entry existed: the step is read from the eval log.
LEGACY_EVAL_STEP = -1


def class_path(cls: type) -> str:
    """The dotted name by which a fingerprint records a class.

    A class of one of :mod:`mcrs.experiment`'s rooms keeps the flat name it had before the rooms
    (``mcrs.experiment.algorithms.QMIX``, not ``mcrs.experiment.training.algorithms.QMIX``), so that
    checkpoints and records written before them still match."""
    parts = cls.__module__.split(".")
    if len(parts) == 4 and parts[:2] == ["mcrs", "experiment"] and parts[2] in ROOMS:
        parts = [*parts[:2], parts[3]]
    return ".".join([*parts, cls.__qualname__])
