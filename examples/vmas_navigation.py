"""Our QPLEX and QMIX (in TorchRL's QMixerLoss and in our loss) against TorchRL's QMixer on VMAS navigation.

    pip install -e ".[vmas]"     # or: pip install vmas
    .venv/bin/python examples/vmas_navigation.py [--frames 48000] [--seed 0] [--learners ...]

VMAS is a task we did not write; everything around the mixers is TorchRL's own: ``VmasEnv``, ``StepCounter``,
``QValueActor`` over ``MultiAgentMLP``, ``EGreedyModule``, ``Collector``, ``ReplayBuffer``, ``QMixerLoss``,
``HardUpdate``. Episodes end early when every agent is on its goal. See :mod:`mcrs.tasks.vmas_navigation`
for the learners; each line prints the greedy team return on 64 fixed evaluation episodes before and after
training. ``tests/test_vmas_navigation.py`` runs a short version.
"""

from __future__ import annotations

import argparse
import logging

import torch

from mcrs.tasks.vmas_navigation import LEARNERS, train_on_vmas


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=48_000, help="env steps (x agents) per learner")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--learners", nargs="+", default=list(LEARNERS), choices=LEARNERS)
    parser.add_argument(
        "--threads", type=int, default=1, help="torch CPU threads (small tensors: 1 is fastest)"
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    logging.getLogger("torchrl").setLevel(logging.WARNING)

    print(
        f"VMAS navigation, {args.frames} frames, seed {args.seed}: greedy team return, untrained -> trained"
    )
    for learner in args.learners:
        r = train_on_vmas(learner, frames=args.frames, seed=args.seed)
        print(
            f"{learner:>17}: {r['untrained_return']:6.2f} -> {r['trained_return']:6.2f}"
            f"  ({r['updates']} updates, {r['seconds']:.0f} s)",
            flush=True,
        )


if __name__ == "__main__":
    main()
