"""Tasks other than MCRS-LCR: the matrix game, any PettingZoo parallel env and VMAS scenarios (conf/task/)."""

from mcrs.tasks.matrix_game import (
    PAYOFF,
    QPLEX_MATRIX_GAME,
    MatrixGameEnv,
    MatrixGameTask,
    make_matrix_game,
)
from mcrs.tasks.pettingzoo import PettingZooTask
from mcrs.tasks.vmas import VmasTask

__all__ = [
    "PAYOFF",
    "QPLEX_MATRIX_GAME",
    "MatrixGameEnv",
    "MatrixGameTask",
    "PettingZooTask",
    "VmasTask",
    "make_matrix_game",
]
