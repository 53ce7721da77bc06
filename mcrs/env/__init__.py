"""The MCRS-LCR environment: belief maths, communication and fusion, the batched simulator and adapters."""

from mcrs.env.config import SCENARIOS, EnvConfig, scenario
from mcrs.env.core import METRICS, MOVES, N_ACTIONS, SURROUNDING, MCRSCore, StepResult
from mcrs.env.pettingzoo_env import MCRSParallelEnv
from mcrs.env.torchrl_env import MCRSEnv

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
