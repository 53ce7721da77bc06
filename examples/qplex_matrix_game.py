"""QPLEX, QMIX and VDN on the one-step matrix game of the QTRAN and QPLEX papers, with our TorchRL pipeline.

    .venv/bin/python examples/qplex_matrix_game.py [--updates 800] [--seed 5] [--mixers qplex qmix vdn]

The task is :class:`mcrs.tasks.MatrixGameEnv` (agent group ``"players"``, state ``"global_state"``), not
MCRS: the same collector, acting policy, episode replay and :class:`~mcrs.objectives.ValueFactorisationLoss`
run on it through their configurable keys. Exploration is uniform throughout, as in the papers. Expected:
QPLEX's greedy joint action is the optimum (0, 0) with Q_tot close to 8; QMIX and VDN, monotonic, settle on
a safe joint action of payoff 0 (QPLEX is seed-sensitive here; see ``tests/test_matrix_game.py``).
"""

from __future__ import annotations

import argparse
import logging
from typing import Any

import torch

from mcrs.models.mixers import MIXERS
from mcrs.tasks.matrix_game import PAYOFF, QPLEX_MATRIX_GAME, train_on_matrix_game


def mixer_kwargs(name: str) -> dict[str, Any]:
    """QPLEX with its own matrix-game settings (10 heads of 3-layer advantage extractors)."""
    return dict(QPLEX_MATRIX_GAME) if name == "qplex" else {}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--updates", type=int, default=800, help="gradient updates per mixer")
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--mixers", nargs="+", default=["qplex", "qmix", "vdn"], choices=MIXERS)
    parser.add_argument(
        "--threads", type=int, default=1, help="torch CPU threads (small tensors: 1 is fastest)"
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    logging.getLogger("torchrl").setLevel(logging.WARNING)

    print(f"payoff (rows: player 0, columns: player 1)\n{PAYOFF}\n")
    for name in args.mixers:
        result = train_on_matrix_game(name, args.updates, args.seed, mixer_kwargs=mixer_kwargs(name))
        print(
            f"{name:>5}: greedy joint action {result['greedy_action']}, Q_tot {result['greedy_q_tot']:.2f}, "
            f"payoff {result['greedy_payoff']:.0f}  (table MSE {result['table_mse']:.2f}, {result['seconds']:.1f} s)"
        )
        with torch.no_grad():
            print(f"       learned Q_tot:\n{result['q_tot'].numpy().round(2)}\n")


if __name__ == "__main__":
    main()
