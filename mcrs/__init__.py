"""MCRS: multi-UAV reconnaissance and search with a limited communication range (Drones 2024, 8, 393).

    import mcrs
    experiment = mcrs.Experiment(mcrs.compose("algo=cnn_semu", "env=map20"), "outputs/my_run")
    experiment.run()

The names here load lazily, so ``import mcrs.env`` stays free of the training stack.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

_LAZY = {
    "Experiment": "mcrs.experiment.training.trainer",
    "Callback": "mcrs.experiment.training.callbacks",
    "Config": "mcrs.experiment.config",
    "compose": "mcrs.experiment.config",
    "Task": "mcrs.experiment.training.task",
    "MCRSTask": "mcrs.experiment.training.task",
}
__all__ = sorted(_LAZY)


def __getattr__(name: str) -> Any:
    if name not in _LAZY:
        raise AttributeError(f"module 'mcrs' has no attribute {name!r}")
    return getattr(import_module(_LAZY[name]), name)
