"""QPLEX, QMIX and VDN on the one-step matrix game of the QTRAN and QPLEX papers, with our TorchRL pipeline.

    .venv/bin/python examples/qplex_matrix_game.py [--updates 800] [--seed 5] [--mixers qplex qmix vdn]

The task is :class:`mcrs.tasks.MatrixGameEnv` (agent group ``"players"``, state ``"global_state"``), not
MCRS: the same collector, acting policy, episode replay and :class:`~mcrs.objectives.ValueFactorisationLoss`
run on it through their configurable keys: :func:`train_on_matrix_game` below is that pipeline written out,
one screen from collector to optimiser (``mcrs.Experiment`` runs the same parts on any task:
``Experiment(config, run_dir, task=MatrixGameTask())``). Exploration is uniform throughout, as in the papers. Expected:
QPLEX's greedy joint action is the optimum (0, 0) with Q_tot close to 8; QMIX and VDN, monotonic, settle on
a safe joint action of payoff 0 (QPLEX is seed-sensitive here; see ``tests/test_matrix_game.py``).
"""

from __future__ import annotations

import argparse
import logging
import time
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.collectors import Collector
from torchrl.objectives import HardUpdate

from mcrs.experiment.training.replay import episodes_from_rollout, make_episode_buffer
from mcrs.models.acting import make_acting_policy
from mcrs.models.agent import RecurrentAgent
from mcrs.models.mixers import MIXERS, make_mixer
from mcrs.objectives import ValueFactorisationLoss
from mcrs.objectives.gradient import gradient_step
from mcrs.tasks.matrix_game import (
    GROUP,
    PAYOFF,
    QPLEX_MATRIX_GAME,
    STATE_KEY,
    STEP_KEYS,
    MatrixGameEnv,
    joint_action_values,
    make_matrix_game,
)


def train_on_matrix_game(
    mixer: str = "qplex",
    updates: int = 800,
    seed: int = 0,
    *,
    mixer_kwargs: dict[str, Any] | None = None,
    num_envs: int = 32,
    batch_episodes: int = 128,
    updates_per_batch: int = 4,
    lr: float = 5e-3,
    grad_clip: float = 10.0,
    hidden_dim: int = 32,
    target_update_interval: int = 50,
    device: str | torch.device = "cpu",
) -> dict[str, Any]:
    """Train a value-factorisation learner on the matrix game with uniformly random exploration.

    The whole MCRS pipeline, pointed at other keys: TorchRL ``Collector`` with our acting policy (group
    ``"players"``, epsilon 1 throughout, the standard protocol for this game), :func:`episodes_from_rollout`,
    a TorchRL replay buffer, :class:`ValueFactorisationLoss` with :meth:`~LossModule.set_keys`, ``HardUpdate``.
    ``mixer_kwargs`` go to :func:`~mcrs.models.mixers.make_mixer` (e.g. :data:`QPLEX_MATRIX_GAME`).

    Returns a dict with the greedy joint action of the trained agents (``greedy_action``), its ``Q_tot``
    (``greedy_q_tot``) and payoff (``greedy_payoff``), the whole ``q_tot`` table, its mean squared error to
    the payoff (``table_mse``: what uniform exploration makes the loss estimate), the last batch's ``loss``
    and the wall-clock ``seconds``.
    """
    start = time.perf_counter()
    torch.manual_seed(seed)
    env = make_matrix_game(num_envs, hidden_dim, device=device)
    base: MatrixGameEnv = env.base_env
    N, A = base.n_players, base.n_actions
    agent = RecurrentAgent(N, A, N, hidden_dim, agent_id=False, last_action=True).to(device)  # obs = id
    state_shape = base.observation_spec[STATE_KEY].shape[1:]
    mix = make_mixer(mixer, N, state_shape, A, device=device, **(mixer_kwargs or {}))
    loss = ValueFactorisationLoss(agent, mix, gamma=0.99, td_lambda=0.0, double_q=True)
    loss.set_keys(
        observation=(GROUP, "observation"),
        action=(GROUP, "action"),
        action_mask=(GROUP, "action_mask"),
        state=STATE_KEY,
    )
    greedy, exploring, _ = make_acting_policy(agent, A, eps_start=1.0, eps_end=1.0, group=GROUP)
    params = [*agent.parameters(), *mix.parameters()]
    optimizer = torch.optim.Adam(params, lr=lr)
    target_updater = HardUpdate(loss, value_network_update_interval=target_update_interval)
    replay = make_episode_buffer(capacity=4096, batch_size=batch_episodes, device=device)
    collector = Collector(
        env,
        exploring,
        frames_per_batch=num_envs,  # one step per env: every batch row is one whole episode
        total_frames=-1,
        device=device,
        trust_policy=True,
        auto_register_policy_transforms=False,
    )

    def to_episodes(batch: TensorDictBase) -> TensorDictBase:
        return episodes_from_rollout(batch, step_keys=STEP_KEYS, action_key=(GROUP, "action"))

    last = torch.tensor(float("nan"))
    try:
        batches = iter(collector)
        for update in range(updates):
            if update % updates_per_batch == 0:
                replay.extend(to_episodes(next(batches)))
            out = loss(replay.sample())
            gradient_step(out["loss"], optimizer, params, grad_clip, step=update)
            target_updater.step()
            last = out["loss"].detach()
    finally:
        collector.shutdown()

    with torch.no_grad():
        rollout = env.rollout(1, greedy)  # [E, 1]: the trained agents' greedy move
    q_tot = joint_action_values(loss, to_episodes(rollout))
    greedy_action = tuple(rollout.get((GROUP, "action"))[0, 0].tolist())
    return {
        "mixer": mixer,
        "greedy_action": greedy_action,
        "greedy_q_tot": float(q_tot[greedy_action]),
        "greedy_payoff": float(base.payoff[greedy_action]),
        "q_tot": q_tot,
        "table_mse": float((q_tot - base.payoff).pow(2).mean()),
        "loss": float(last),
        "seconds": time.perf_counter() - start,
    }


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
