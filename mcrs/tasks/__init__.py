"""Small TorchRL multi-agent tasks other than MCRS-LCR, to check that our mixers and loss are task-agnostic."""

from mcrs.tasks.matrix_game import (
    PAYOFF,
    QPLEX_MATRIX_GAME,
    MatrixGameEnv,
    MatrixGameTask,
    make_matrix_game,
    train_on_matrix_game,
)

__all__ = [
    "PAYOFF",
    "QPLEX_MATRIX_GAME",
    "MatrixGameEnv",
    "MatrixGameTask",
    "make_matrix_game",
    "train_on_matrix_game",
]
