"""Checkpoint cost with a full replay (``mcrs-bench-checkpoint``).

Why: a map20 run at the pymarl preset holds 5000 episodes (about 3.3 GB) in its replay; written whole
into every checkpoint, that is expensive in time and disk, so an interrupted campaign loses more work
between checkpoints. The replay is saved incrementally (:mod:`mcrs.experiment.replay_store`); this
times the real :meth:`Trainer.save` of a run whose replay is full:

1. the first checkpoint, which writes every block (what any checkpoint cost before);
2. a checkpoint after ``--new-episodes`` more episodes (default: the 1000 episodes of the preset's
   100k-step checkpoint interval on map20), which rewrites only their blocks; goal: <= 10 s;
3. with ``--compare-inline``, the previous format: the whole replay inline in one file.

The episodes are synthetic but valid (:func:`mcrs.benchmarks.learner.synthetic_episodes`): the cost of
writing them does not depend on their values. Everything is written under a temporary directory.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import torch

from mcrs.benchmarks.common import benchmark_process, load_average, pass_fail
from mcrs.benchmarks.learner import compose_config, synthetic_episodes
from mcrs.env.config import SCENARIOS, from_mapping
from mcrs.experiment import checkpoint as ckpt

GOAL_SECONDS = 10.0
GOAL_MAP = "map20"
CHUNK = 250  # synthetic episodes generated at a time


def _fill(trainer, n: int, generator: torch.Generator) -> None:
    """Add ``n`` synthetic episodes through the trainer's own path (replay + store bookkeeping)."""
    env_config = from_mapping(trainer.cfg.env)
    while n > 0:
        k = min(CHUNK, n)
        trainer.replay_store.mark_written(trainer.replay.extend(synthetic_episodes(k, env_config, generator)))
        n -= k


def _size_gib(paths: Sequence[Path]) -> float:
    return sum(p.stat().st_size for p in paths) / 2**30


def _parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="mcrs-bench-checkpoint",
        description="Seconds to write a checkpoint of a run whose replay is full (incremental replay).",
    )
    parser.add_argument("--map", choices=SCENARIOS, default=GOAL_MAP)
    parser.add_argument(
        "--new-episodes", type=int, default=1000, help="episodes added between the two timed checkpoints"
    )
    parser.add_argument("--compare-inline", action="store_true", help="also time the whole replay inline")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads (0: torch's default)")
    parser.add_argument("--quick", action="store_true", help="tiny episodes and replay: a smoke test")
    args = parser.parse_args(argv)
    if args.new_episodes < 1:
        parser.error(f"--new-episodes must be >= 1, got {args.new_episodes}")
    if args.threads < 0:
        parser.error(f"--threads must be >= 0, got {args.threads}")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    command = shlex.join(["mcrs-bench-checkpoint", *(sys.argv[1:] if argv is None else argv)])
    args = _parse_args(argv)
    with benchmark_process(args.threads):
        _run(args, command)
    return 0


def _run(args: argparse.Namespace, command: str) -> None:
    from mcrs.experiment.experiment import Experiment

    extra = ["logger=csv", "logger.progress_bar=false", f"threads={args.threads}"]
    cfg = compose_config(args.map, args.quick, extra)
    capacity = int(cfg.train.replay_episodes)
    new = min(args.new_episodes, capacity)
    print(
        f"MCRS checkpoint benchmark: device=cpu, torch threads={torch.get_num_threads()}, cpus={os.cpu_count()}, "
        f"load average {load_average()}\ncommand: {command}\n"
        f"{args.map}, pymarl preset (QMIX): Trainer.save() with a full replay of {capacity:,} episodes",
        flush=True,
    )
    with tempfile.TemporaryDirectory(prefix="mcrs-bench-checkpoint-") as run_dir:
        trainer = Experiment(cfg, run_dir)
        generator = torch.Generator().manual_seed(0)
        start = time.perf_counter()
        _fill(trainer, capacity, generator)
        print(
            f"replay filled with {capacity:,} synthetic episodes in {time.perf_counter() - start:.1f} s",
            flush=True,
        )
        checkpoints = Path(run_dir) / "checkpoints"

        start = time.perf_counter()
        trainer.save()
        first = time.perf_counter() - start
        blocks = sorted(checkpoints.glob("replay_*.pt"))
        print(
            f"first checkpoint (every replay block written): {first:.2f} s, {len(blocks)} block files, "
            f"{_size_gib(blocks):.2f} GiB; last.pt {ckpt.checkpoint_path(run_dir).stat().st_size / 2**20:.1f} MiB "
            f"(load average {load_average()})",
            flush=True,
        )
        _fill(trainer, new, generator)
        trainer.counters.env_steps += new * int(cfg.env.max_steps)  # names the weights file apart
        start = time.perf_counter()
        trainer.save()
        incremental = time.perf_counter() - start
        written = [p for p in checkpoints.glob("replay_*.pt") if p not in blocks]
        print(
            f"checkpoint after {new:,} new episodes (blocks rewritten: {len(written)}, "
            f"{_size_gib(written):.2f} GiB): {incremental:.2f} s (load average {load_average()})",
            flush=True,
        )
        if args.compare_inline:
            start = time.perf_counter()
            path = ckpt.save_atomic(trainer.state_dict(replay_inline=True), Path(run_dir) / "inline.pt")
            inline = time.perf_counter() - start
            print(
                f"the previous format, the whole replay inline in last.pt: {inline:.2f} s, "
                f"{path.stat().st_size / 2**30:.2f} GiB (load average {load_average()})",
                flush=True,
            )
    judged = args.map == GOAL_MAP and not args.quick
    verdict = pass_fail(incremental <= GOAL_SECONDS) if judged else "not judged (map20 without --quick only)"
    print(
        f"\ncheckpoint of a run holding a full {args.map} replay ({capacity:,} episodes): {incremental:.2f} s "
        f"(goal <= {GOAL_SECONDS:g} s: {verdict})",
        flush=True,
    )


if __name__ == "__main__":
    raise SystemExit(main())
