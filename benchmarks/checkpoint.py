"""Checkpoint cost with a full replay (``mcrs-bench-checkpoint``).

Why: a map20 run at the pymarl preset holds 5000 episodes (about 3.3 GB) in its replay; written whole
into every checkpoint, that is expensive in time and disk, so an interrupted campaign loses more work
between checkpoints. The replay is saved incrementally (:mod:`mcrs.experiment.run.replay_store`); this
times the real :meth:`Experiment.save` of a run whose replay is full:

1. the first checkpoint, which writes every block (what any checkpoint cost before);
2. a checkpoint after ``--new-episodes`` more episodes (default: the 1000 episodes of the preset's
   100k-step checkpoint interval on map20), which rewrites only their blocks; goal: <= 10 s (JSON figure
   ``checkpoint_seconds``);
3. with ``--compare-inline``, the previous format: the whole replay inline in one file.

The episodes are synthetic but valid (:func:`mcrs_benchmarks.common.synthetic_episodes`): the cost of
writing them does not depend on their values. Everything is written under a temporary directory.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from mcrs_benchmarks.common import compose_config, load_average, synthetic_episodes
from mcrs_benchmarks.harness import Goal, Report, make_parser, require_at_least, run_benchmark

from mcrs.env.config import SCENARIOS, from_mapping
from mcrs.experiment.run import checkpoint as ckpt

if TYPE_CHECKING:
    from mcrs.experiment.training.trainer import Experiment

GOAL_SECONDS = 10.0
GOAL_MAP = "map20"
CHUNK = 250  # synthetic episodes generated at a time


def _fill(trainer: Experiment, n: int, generator: torch.Generator) -> None:
    """Add ``n`` synthetic episodes through the trainer's own path (replay + store bookkeeping)."""
    env_config = from_mapping(trainer.config.env)
    while n > 0:
        k = min(CHUNK, n)
        trainer.replay_store.mark_written(trainer.replay.extend(synthetic_episodes(k, env_config, generator)))
        n -= k


def _size_gib(paths: Sequence[Path]) -> float:
    return sum(p.stat().st_size for p in paths) / 2**30


def _parser() -> argparse.ArgumentParser:
    parser = make_parser(
        "mcrs-bench-checkpoint",
        "Seconds to write a checkpoint of a run whose replay is full (incremental replay).",
        threads=1,
        quick="tiny episodes and replay: a smoke test",
    )
    parser.add_argument("--map", choices=SCENARIOS, default=GOAL_MAP)
    parser.add_argument(
        "--new-episodes", type=int, default=1000, help="episodes added between the two timed checkpoints"
    )
    parser.add_argument("--compare-inline", action="store_true", help="also time the whole replay inline")
    return parser


def _validate(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    require_at_least(parser, args, 1, "new_episodes")


def main(argv: Sequence[str] | None = None) -> int:
    return run_benchmark(_parser(), argv, _run, _validate)


def _time_checkpoints(trainer: Experiment, run_dir: Path, args: argparse.Namespace, report: Report) -> float:
    """Fill the replay, time the first and an incremental checkpoint (and, if asked, the inline format);
    return the incremental checkpoint's seconds."""
    cfg = trainer.config
    capacity = int(cfg.train.replay_episodes)
    new = min(args.new_episodes, capacity)
    generator = torch.Generator().manual_seed(0)
    start = time.perf_counter()
    _fill(trainer, capacity, generator)
    fill = report.figure("fill_seconds", time.perf_counter() - start, "s")
    print(f"replay filled with {capacity:,} synthetic episodes in {fill.value:.1f} s", flush=True)
    checkpoints = run_dir / "checkpoints"

    start = time.perf_counter()
    trainer.save()
    first = report.figure("first_seconds", time.perf_counter() - start, "s")
    blocks = sorted(checkpoints.glob("replay_*.pt"))
    report.figure("first_blocks", len(blocks), "files")
    report.figure("first_gib", _size_gib(blocks), "GiB")
    last_mib = report.figure("last_pt_mib", ckpt.checkpoint_path(run_dir).stat().st_size / 2**20, "MiB")
    print(
        f"first checkpoint (every replay block written): {first.value:.2f} s, {len(blocks)} block files, "
        f"{_size_gib(blocks):.2f} GiB; last.pt {last_mib.value:.1f} MiB (load average {load_average()})",
        flush=True,
    )
    _fill(trainer, new, generator)
    trainer.counters.env_steps += new * int(cfg.env.max_steps)  # names the weights file apart
    start = time.perf_counter()
    trainer.save()
    incremental = time.perf_counter() - start
    written = [p for p in checkpoints.glob("replay_*.pt") if p not in blocks]
    report.figure("new_episodes", new, "episodes")
    report.figure("incremental_blocks", len(written), "files")
    report.figure("incremental_gib", _size_gib(written), "GiB")
    print(
        f"checkpoint after {new:,} new episodes (blocks rewritten: {len(written)}, "
        f"{_size_gib(written):.2f} GiB): {incremental:.2f} s (load average {load_average()})",
        flush=True,
    )
    if args.compare_inline:
        start = time.perf_counter()
        path = ckpt.save_atomic(trainer.state_dict(replay_inline=True), run_dir / "inline.pt")
        inline = report.figure("inline_seconds", time.perf_counter() - start, "s")
        inline_gib = report.figure("inline_gib", path.stat().st_size / 2**30, "GiB")
        print(
            f"the previous format, the whole replay inline in last.pt: {inline.value:.2f} s, "
            f"{inline_gib.value:.2f} GiB (load average {load_average()})",
            flush=True,
        )
    return incremental


def _run(args: argparse.Namespace, report: Report) -> None:
    """Fill a replay, time the first and an incremental checkpoint (and the inline format), judge the goal."""
    from mcrs.experiment.training.trainer import Experiment

    extra = ["logger=csv", "logger.progress_bar=false", f"threads={args.threads}"]
    cfg = compose_config(args.map, args.quick, extra)
    capacity = int(cfg.train.replay_episodes)
    report.header("checkpoint benchmark")
    print(
        f"{args.map}, pymarl preset (QMIX): Experiment.save() with a full replay of {capacity:,} episodes",
        flush=True,
    )
    report.figure("replay_episodes", capacity, "episodes")
    with tempfile.TemporaryDirectory(prefix="mcrs-bench-checkpoint-") as run_dir:
        trainer = Experiment(cfg, run_dir)
        try:
            incremental = _time_checkpoints(trainer, Path(run_dir), args, report)
        finally:
            trainer.close()  # the run directory's lock, before the directory goes
    judged = args.map == GOAL_MAP and not args.quick
    fig = report.figure(
        "checkpoint_seconds",
        incremental,
        "s",
        Goal("<=", GOAL_SECONDS),
        not_judged="" if judged else "map20 without --quick only",
    )
    print(
        f"\ncheckpoint of a run holding a full {args.map} replay ({capacity:,} episodes): {incremental:.2f} s "
        f"(goal <= {GOAL_SECONDS:g} s: {fig.verdict})",
        flush=True,
    )


if __name__ == "__main__":
    raise SystemExit(main())
