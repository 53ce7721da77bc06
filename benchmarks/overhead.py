"""Whole-run cost of the episodic memory (``mcrs-bench-overhead``): CNN-SEMU against QMIX, same env steps.

Why: the memory must cost close to nothing next to the learner (goal: a CNN-SEMU run at most 1.3x QMIX's
wall clock on map20 for the same env steps; JSON figure ``ratio``, printed as ``CNN_SEMU vs QMIX: X.XXx``).
A 2M-step run takes hours, so this measures and projects:

1. The real :class:`~mcrs.experiment.training.trainer.Experiment` of each algorithm runs ``--loop-steps`` env steps
   (pymarl preset; the memory inserts every batch, attaches look-ups to every learner batch and trains
   phi every ``t_emb`` = 10k steps, all inside the timed window), exactly as
   :func:`mcrs_benchmarks.loop.measure_loop` times QMIX; evaluation is timed apart and added back at
   the preset's interval for both.
2. What a short window cannot show grows with the buffer: re-embedding after every training of phi costs
   time per stored state, and the buffer holds min(env steps, capacity) states. A synthetic buffer of
   ``--entries`` states (1M: the capacity) is filled and re-embedded to get the cost per state, and the
   projection adds ``sum_k cost_per_state * (min(k t_emb, capacity) - size during the window)`` over the
   run's trainings of phi. Insertion into a full 1M buffer is timed too and charged for every batch after
   the window (conservative: the window's own insertions are already in its rate).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence

from mcrs_benchmarks.common import compose_config, load_average
from mcrs_benchmarks.harness import Goal, Report, make_parser, require_at_least, run_benchmark
from mcrs_benchmarks.loop import GOAL_STEPS, LoopResult, measure_loop
from mcrs_benchmarks.memory import fill, median_seconds, rollout

from mcrs.env.config import SCENARIOS, from_mapping
from mcrs.experiment.training.episodic import build_embedding
from mcrs.memory.codec import StateCodec
from mcrs.memory.delta import match_tolerance
from mcrs.memory.episodic import EpisodicMemory

GOAL_RATIO = 1.3
#: Goals of other algorithms than CNN-SEMU: EMC trains two more recurrent learners (curiosity).
GOAL_RATIOS = {"emc": 2.0}
GOAL_MAP = "map20"
DEFAULT_LOOP_STEPS = 60_000


def reembed_and_insert_cost(
    map_name: str, algo: str, entries: int, quick: bool = False
) -> tuple[float, float, int, int]:
    """(seconds per re-embedded state, seconds per insertion of one collector batch into a full buffer,
    t_emb, capacity) for ``algo``'s embedding and memory settings."""
    cfg = compose_config(map_name, quick, algo=algo)
    env_config = from_mapping(cfg.env)
    mem = cfg.algo.memory
    memory = EpisodicMemory(
        build_embedding(cfg, env_config).eval(),
        StateCodec(env_config),
        capacity=entries,
        tolerance=match_tolerance(mem.delta, str(mem.delta_rule), str(mem.neighbourhood), mem.key_dim),
        gamma=cfg.algo.gamma,
        max_steps=env_config.max_steps,
    )
    fill(memory, env_config, entries, seed=1)
    start = time.perf_counter()
    memory.refresh_keys()
    per_state = (time.perf_counter() - start) / entries
    batches = [rollout(env_config, int(cfg.train.num_envs), seed=100 + i) for i in range(4)]
    insert_s, _ = median_seconds(lambda: memory.insert(*batches.pop()), 3)  # (wall, CPU): the wall clock
    return per_state, insert_s, int(mem.embedding_interval), int(mem.capacity)


def project(
    loop: LoopResult, per_state: float, insert_s: float, interval: int, capacity: int, batch_steps: int
) -> tuple[float, float]:
    """(hours of a whole run with evaluation, of which the buffer-growth term) for GOAL_STEPS env steps."""
    window_size = loop.total_steps / 2  # mean buffer size at the window's trainings of phi (one entry/step)
    growth = sum(
        per_state * max(0.0, min(k * interval, capacity) - window_size)
        for k in range(1, GOAL_STEPS // interval + 1)
    )
    inserts = insert_s * max(0, GOAL_STEPS - loop.total_steps) / batch_steps
    extra = growth + inserts
    return loop.hours(GOAL_STEPS, True) + extra / 3600, extra / 3600


def _parser() -> argparse.ArgumentParser:
    parser = make_parser(
        "mcrs-bench-overhead",
        "Whole-run wall clock of a memory algorithm against QMIX (measured window + projection).",
        quick="tiny episodes and batches: a smoke test",
    )
    parser.add_argument("--map", choices=SCENARIOS, default=GOAL_MAP)
    parser.add_argument("--algo", default="cnn_semu", help="the memory algorithm compared with qmix")
    parser.add_argument("--loop-steps", type=int, default=DEFAULT_LOOP_STEPS, help="env steps per timed run")
    parser.add_argument("--entries", type=int, default=1_000_000, help="states of the re-embedding probe")
    return parser


def _validate(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    require_at_least(parser, args, 1, "loop_steps", "entries")


def main(argv: Sequence[str] | None = None) -> int:
    return run_benchmark(_parser(), argv, _run, _validate)


def _run(args: argparse.Namespace, report: Report) -> None:
    report.header("memory overhead benchmark")
    print(
        f"{args.map}, pymarl preset; each algorithm's real Experiment for {args.loop_steps:,} env steps "
        "(steady-state window, evaluation timed apart), then a projection to "
        f"{GOAL_STEPS / 1e6:g}M env steps",
        flush=True,
    )
    cfg = compose_config(args.map, args.quick)
    batch_steps = int(cfg.train.num_envs) * int(cfg.env.max_steps)
    loops = {
        algo: measure_loop(args.map, args.quick, args.loop_steps, args.threads, algo=algo)
        for algo in ("qmix", args.algo)
    }
    per_state, insert_s, interval, capacity = reembed_and_insert_cost(
        args.map, args.algo, args.entries, args.quick
    )
    report.figure("reembed_us_per_state", per_state * 1e6, "us")
    report.figure(
        "insert_ms",
        insert_s * 1e3,
        "ms",
        note=f"one collector batch into a full {args.entries:,}-entry buffer",
    )
    print(
        f"\nre-embedding probe: {args.entries:,} states, {per_state * 1e6:.2f} us/state "
        f"({per_state * capacity:.2f} s for a full buffer of {capacity:,}); insertion of one collector batch "
        f"({batch_steps:,} transitions) into the full probe buffer: {insert_s * 1e3:.1f} ms",
        flush=True,
    )
    print(
        f"\n{'algo':<10} {'env-steps/s':>12} {'s/update':>9} {'2M h (window+eval)':>19} {'+growth h':>10} {'2M h':>7}"
    )
    hours = {}
    for algo, loop in loops.items():
        per_update = loop.update_seconds / loop.updates if loop.updates else float("nan")
        if algo == "qmix":
            total, extra = loop.hours(GOAL_STEPS, True), 0.0
        else:
            total, extra = project(loop, per_state, insert_s, interval, capacity, batch_steps)
        hours[algo] = total
        window_hours = loop.hours(GOAL_STEPS, True)
        report.row(
            "algorithms", algo=algo, env_steps_per_s=loop.env_steps_per_s, seconds_per_update=per_update,
            hours_window_eval=window_hours, hours_growth=extra, hours=total,
        )  # fmt: skip
        report.figure(f"{algo}.env_steps_per_s", loop.env_steps_per_s, "env-steps/s")
        report.figure(f"{algo}.hours", total, "h", note=f"projected whole {GOAL_STEPS / 1e6:g}M-step run")
        print(
            f"{algo:<10} {loop.env_steps_per_s:>12,.0f} {per_update:>9.4f} {window_hours:>19.2f} "
            f"{extra:>10.2f} {total:>7.2f}",
            flush=True,
        )
    window_ratio = loops["qmix"].env_steps_per_s / loops[args.algo].env_steps_per_s
    report.figure("window_ratio", window_ratio, "x", note=f"{args.algo} / qmix, measured window only")
    judged = args.map == GOAL_MAP and not args.quick
    goal = GOAL_RATIOS.get(args.algo, GOAL_RATIO)
    ratio = report.figure(
        "ratio",
        hours[args.algo] / hours["qmix"],
        "x",
        Goal("<=", goal),
        not_judged="" if judged else "map20 without --quick only",
        note=f"{args.algo} / qmix, whole {GOAL_STEPS / 1e6:g}M run",
    )
    print(
        f"\nratio {args.algo} / qmix: window {window_ratio:.2f}x; whole {GOAL_STEPS / 1e6:g}M run "
        f"{ratio.value:.2f}x (goal <= {goal:g}x: {ratio.verdict})\n"
        f"{args.algo.upper()} vs QMIX: {ratio.value:.2f}x (whole run, {args.map}, load average {load_average()})",
        flush=True,
    )


if __name__ == "__main__":
    raise SystemExit(main())
