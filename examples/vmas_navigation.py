"""QMIX (or any of our learners) on VMAS navigation through the experiment, against the random baseline.

    pip install -e ".[vmas]"     # or: pip install vmas
    .venv/bin/python examples/vmas_navigation.py [--steps 48000] [--seed 0] [--algo qmix] [--out outputs/vmas]

VMAS is a task we did not write: :class:`mcrs.tasks.vmas.VmasTask` puts it in the experiment's key contract
(per-agent rewards summed into the team's, episodes that end early when every agent is on its goal padded in
the replay, the joined observations as the mixer's state), and ``mcrs.Experiment`` trains it with the same
loop, checkpoints and logs as MCRS. The command line is the same run: ``mcrs-train task=vmas_navigation
algo=qmix``. The script ends with the trained agent and the random baseline on the same 64 episodes
(``mcrs-eval policy=<run dir>`` does the same from the shell).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import mcrs
from mcrs.policies.task_runs import evaluate_task_run, load_task_run
from mcrs.tasks.vmas import VmasTask


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=48_000, help="env steps (a multiple of 800)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--algo", default="qmix", choices=["qmix", "vdn", "qplex"])
    parser.add_argument("--out", default="outputs/vmas_navigation")
    args = parser.parse_args()
    logging.getLogger("torchrl").setLevel(logging.WARNING)

    task = VmasTask("navigation", 50, {"n_agents": 3, "collisions": False, "shared_rew": False})
    config = mcrs.compose(
        f"algo={args.algo}",
        f"seed={args.seed}",
        f"train.total_env_steps={args.steps}",
        "train.num_envs=16",  # 16 episodes of 50 steps a batch: 800 env steps
        "train.batch_episodes=32",
        f"train.eval_interval={max(args.steps // 6 // 800, 1) * 800}",
        "train.eval_episodes=64",
        f"train.eps_anneal_steps={args.steps // 3}",
        "train.optimizer=adam",
        "train.lr=0.001",
        "train.target_update_episodes=100",
        "threads=1",
    )
    config.overwrite = True
    run_dir = Path(args.out)
    mcrs.Experiment(config, run_dir, task=task).run()
    table = evaluate_task_run(load_task_run(run_dir), 64, seed=1, label=f"{args.algo} ({args.steps} steps)")
    for name, metrics in table.items():
        print(
            f"{name:>24}: team return {float(metrics['episode_reward'].mean()):6.2f}, episode length "
            f"{float(metrics['episode_length'].mean()):5.1f} (of 50)"
        )


if __name__ == "__main__":
    main()
