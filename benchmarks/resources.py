"""Long-run resource benchmark (``mcrs-bench-resources``, ``python -m mcrs_benchmarks.resources``).

Why: a 2M-step run must not grow its memory without bound. Every store of the loop is bounded (the replay
buffer holds ``train.replay_episodes`` episodes, the episodic memory ``algo.memory.capacity`` entries), so
once they are full the process's resident memory (RSS) should stay flat; a leak (a growing list of stats,
tensors kept alive by a logger, a collector that accumulates) shows as growth after that point.

This trains in-process (default: map10, QMIX, 200k env steps, a replay of 500 episodes so that it fills in
the first eighth of the run), samples the RSS (VmRSS of /proc/self/status, or psutil; after
``gc.collect()`` and glibc's ``malloc_trim(0)``, so that freed allocator cache is not read as growth) every
``--every`` env steps and prints the curve (env steps, RSS, replay episodes, memory entries), then the growth between
50% and 100% of the run with PASS/FAIL against < 5% (JSON: figure ``rss_growth_percent``, table ``samples``).
The run directory is a temporary folder, removed at
the end (checkpoints included).

    mcrs-bench-resources                                         # QMIX, map10, 200k env steps
    mcrs-bench-resources --algo cnn_semu --override algo.memory.capacity=20000
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import gc
import tempfile
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

from mcrs_benchmarks.env_throughput import resident_bytes
from mcrs_benchmarks.harness import Goal, Report, make_parser, require_at_least, run_benchmark

GOAL_GROWTH = 0.05  # RSS growth between 50% and 100% of the run
MIB = 2**20


@dataclass
class Sample:
    env_steps: int
    rss_mib: float
    replay_episodes: int
    memory_entries: int


def release_free_heap() -> None:
    """Collect garbage and hand glibc's cached free heap back to the OS (``malloc_trim``).

    Without this, memory freed after a transient peak (a checkpoint's serialisation, an evaluation) stays
    in the process as allocator cache and reads as growth; what is left is memory that is still in use.
    """
    gc.collect()
    with contextlib.suppress(OSError, AttributeError):  # not glibc: the figure includes the allocator's cache
        ctypes.CDLL("libc.so.6").malloc_trim(0)


def rss_bytes() -> int:
    """Resident memory of this process: /proc's VmRSS, else psutil."""
    value = resident_bytes()
    if value is not None:
        return value
    import psutil  # only where there is no /proc (not a dependency)

    return int(psutil.Process().memory_info().rss)


def _parser() -> argparse.ArgumentParser:
    parser = make_parser("mcrs-bench-resources", __doc__.split("\n\n")[0], threads=1)
    parser.add_argument("--algo", default="qmix", help="algo group option (qmix, cnn_semu, ...)")
    parser.add_argument("--env", default="map10", help="env group option (map10, map15, map20)")
    parser.add_argument("--env-steps", type=int, default=200_000, help="length of the run")
    parser.add_argument(
        "--replay-episodes", type=int, default=500, help="replay capacity (small: fills early)"
    )
    parser.add_argument("--every", type=int, default=10_000, help="env steps between RSS samples")
    parser.add_argument(
        "--override",
        action="append",
        default=[],
        help="extra Hydra override, e.g. algo.memory.capacity=20000",
    )
    return parser


def _validate(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    require_at_least(parser, args, 1, "env_steps", "replay_episodes", "every")


def compose(args: argparse.Namespace):
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    from mcrs.experiment.config import register_configs
    from mcrs.train import CONFIG_DIR

    register_configs()
    overrides = [
        f"algo={args.algo}",
        f"env={args.env}",
        f"train.total_env_steps={args.env_steps}",
        f"train.replay_episodes={args.replay_episodes}",
        f"threads={args.threads}",
        "logger.progress_bar=false",
        *args.override,
    ]
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return hydra_compose(config_name="config", overrides=overrides)


def run(args: argparse.Namespace, run_dir: Path) -> tuple[list[Sample], object]:
    """Train, sampling the RSS before every collector batch that crosses a multiple of ``--every`` and after
    the final evaluation and checkpoint (before the collector shuts down, which frees memory)."""
    from mcrs.experiment.training.trainer import Experiment

    trainer = Experiment(compose(args), run_dir)
    samples: list[Sample] = []

    def sample() -> None:
        release_free_heap()
        memory = trainer.callback("memory").memory.size if trainer.config.algo.memory.enabled else 0
        samples.append(
            Sample(trainer.counters.env_steps, rss_bytes() / MIB, len(trainer.replay), int(memory))
        )

    next_sample = [0]
    collect = trainer.collector.next_batch

    def sampled_next_batch(iterator):
        if trainer.counters.env_steps >= next_sample[0]:
            sample()
            next_sample[0] += args.every
        return collect(iterator)

    save = trainer.save

    def save_then_sample(name: str = "last.pt"):
        path = save(name)
        if trainer.counters.env_steps >= args.env_steps:  # the final checkpoint, collector still alive
            if samples and samples[-1].env_steps == trainer.counters.env_steps:
                samples.pop()  # an interval checkpoint at the last step: keep the sample after the last one
            sample()
        return path

    trainer.collector.next_batch = sampled_next_batch  # the loop's one call per collector batch
    trainer.save = save_then_sample
    trainer.run()
    return samples, trainer


def growth(samples: list[Sample], total: int) -> tuple[Sample, Sample, float]:
    """RSS growth from the first sample at or after 50% of the run to the last sample."""
    middle = next(s for s in samples if s.env_steps >= total // 2)
    last = samples[-1]
    return middle, last, (last.rss_mib - middle.rss_mib) / middle.rss_mib


def main(argv: Sequence[str] | None = None) -> int:
    return run_benchmark(_parser(), argv, _report, _validate)


def _report(args: argparse.Namespace, report: Report) -> None:
    report.header(
        "resource benchmark",
        details=f"{args.algo} on {args.env}, {args.env_steps} env steps, replay {args.replay_episodes} episodes, ",
    )
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="mcrs-bench-resources-") as tmp:
        samples, trainer = run(args, Path(tmp) / "run")
    elapsed = report.figure("run_seconds", time.perf_counter() - start, "s")
    print(f"\n{'env_steps':>10} {'rss_mib':>9} {'replay_episodes':>16} {'memory_entries':>15}")
    for s in samples:
        report.row("samples", **asdict(s))
        print(f"{s.env_steps:>10} {s.rss_mib:>9.1f} {s.replay_episodes:>16} {s.memory_entries:>15}")
    middle, last, rise = growth(samples, args.env_steps)
    capacity = trainer.config.train.replay_episodes
    report.figure("replay_full_at_half", middle.replay_episodes >= capacity)
    full = "full" if middle.replay_episodes >= capacity else f"NOT full ({middle.replay_episodes}/{capacity})"
    memory_text = ""
    if trainer.config.algo.memory.enabled:
        report.figure("memory_entries_at_half", middle.memory_entries, "entries")
        memory_text = (
            f"; memory at 50%: {middle.memory_entries}/{trainer.config.algo.memory.capacity} entries"
        )
    print(f"\nrun: {elapsed.value:.0f} s; replay at 50%: {full}{memory_text}")
    report.figure("rss_mib_half", middle.rss_mib, "MiB", note=f"at {middle.env_steps} env steps")
    report.figure("rss_mib_end", last.rss_mib, "MiB", note=f"at {last.env_steps} env steps")
    fig = report.figure(
        "rss_growth_percent", 100 * rise, "%", Goal("<", 100 * GOAL_GROWTH), note="50% -> 100% of the run"
    )
    print(
        f"RSS growth 50% -> 100% ({middle.env_steps} -> {last.env_steps} env steps): "
        f"{middle.rss_mib:.1f} -> {last.rss_mib:.1f} MiB = {fig.value:+.2f}% "
        f"(goal < {100 * GOAL_GROWTH:.0f}%): {fig.verdict}",
        flush=True,
    )


if __name__ == "__main__":
    raise SystemExit(main())
