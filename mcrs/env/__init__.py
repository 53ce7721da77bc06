"""The MCRS-LCR environment: belief maths, communication and fusion, the batched simulator and its adapters.

It is the bottom layer and imports nothing else of ``mcrs``. Every name is imported on first use, so
``import mcrs.env`` loads neither PettingZoo nor torch."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from mcrs.env.config import SCENARIOS, EnvConfig, ScenarioConfig, scenario
    from mcrs.env.core import METRICS, MOVES, N_ACTIONS, SURROUNDING, MCRSCore, StepResult
    from mcrs.env.pettingzoo_env import MCRSParallelEnv
    from mcrs.env.torchrl_env import MCRSEnv

#: Where each exported name lives. ``mcrs.env.config`` loads neither torch, TorchRL nor PettingZoo, so a
#: command line can refuse a config at once.
_EXPORTS = {
    **dict.fromkeys(("SCENARIOS", "EnvConfig", "ScenarioConfig", "scenario"), "mcrs.env.config"),
    **dict.fromkeys(
        ("METRICS", "MOVES", "N_ACTIONS", "SURROUNDING", "MCRSCore", "StepResult"), "mcrs.env.core"
    ),
    "MCRSEnv": "mcrs.env.torchrl_env",
    "MCRSParallelEnv": "mcrs.env.pettingzoo_env",
}

__all__ = [
    "METRICS",
    "MOVES",
    "N_ACTIONS",
    "SCENARIOS",
    "SURROUNDING",
    "EnvConfig",
    "MCRSCore",
    "MCRSEnv",
    "MCRSParallelEnv",
    "ScenarioConfig",
    "StepResult",
    "scenario",
]


def __getattr__(name: str) -> Any:
    """Import an exported name on first use, e.g. ``mcrs.env.MCRSEnv`` with TorchRL."""
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
