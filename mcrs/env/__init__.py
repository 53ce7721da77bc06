"""The MCRS-LCR environment: belief maths, communication and fusion, the batched simulator and adapters.

The bottom layer of the package: it imports nothing else of ``mcrs``. PettingZoo is optional at import
time: ``MCRSParallelEnv`` (the PettingZoo adapter) is imported on first use, so ``import mcrs.env`` does
not load PettingZoo.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from mcrs.env.config import SCENARIOS, EnvConfig, scenario
from mcrs.env.core import METRICS, MOVES, N_ACTIONS, SURROUNDING, MCRSCore, StepResult
from mcrs.env.torchrl_env import MCRSEnv

if TYPE_CHECKING:
    from mcrs.env.pettingzoo_env import MCRSParallelEnv

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
    "StepResult",
    "scenario",
]


def __getattr__(name: str) -> Any:
    """``mcrs.env.MCRSParallelEnv``: the PettingZoo adapter, imported (with PettingZoo) when first asked for."""
    if name == "MCRSParallelEnv":
        from mcrs.env.pettingzoo_env import MCRSParallelEnv

        return MCRSParallelEnv
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
