"""Evaluation metrics of training runs over a window of env steps, and at given steps: a pilot's figures.

    python -m mcrs_lab.analysis.window results/records/pilot --from 11000 --to 80000 --at 672000 --at 1000000

For each training run or record found under the paths (as ``mcrs-report`` finds them), one row: its label
(algorithm and the settings that tell it from the others), seed, the mean of each metric over the
evaluations whose env step lies in ``[--from, --to]``, and each metric at every ``--at`` step (the last
evaluation at or before it; blank when the run has not reached it). ``--metric reward_target_r2`` compares
runs under the two r2 rules like with like.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from mcrs.experiment.util.tables import markdown
from mcrs_lab.analysis.records import RecordError
from mcrs_lab.analysis.runs import TrainingRun, find_runs, run_labels

METRICS = ("episode_reward", "no_fly_violations", "collisions", "false_discoveries", "targets_found")
#: The episode reward as r2 by ``discovery_rule=target`` would have paid it: less w2 per false discovery
#: for a run under eq. 24 (``belief``), the reward itself for a run under ``target``. Compares runs of the
#: two rules like with like.
TARGET_R2 = "reward_target_r2"
CHOICES = (*METRICS, TARGET_R2)


def points_of(run: TrainingRun, metric: str) -> tuple[np.ndarray, np.ndarray] | None:
    """``(steps, values)`` of ``eval/<metric>``, or of :data:`TARGET_R2`; None when the run lacks them."""
    if metric != TARGET_R2:
        return run.scalar(f"eval/{metric}")
    reward, false = run.scalar("eval/episode_reward"), run.scalar("eval/false_discoveries")
    if reward is None:
        return None
    if run.setting("env.discovery_rule") != "belief":
        return reward
    if false is None or not np.array_equal(reward[0], false[0]):
        return None
    weight = float(run.setting("env.w_discovery") or 0.0)
    return reward[0], reward[1] - weight * false[1]


def window_mean(run: TrainingRun, metric: str, low: int, high: int) -> float | None:
    """The mean of ``eval/<metric>`` over the evaluations with ``low <= step <= high``; None if there is none."""
    points = points_of(run, metric)
    if points is None:
        return None
    steps, values = points
    inside = (steps >= low) & (steps <= high)
    return float(np.mean(values[inside])) if inside.any() else None


def value_at(run: TrainingRun, metric: str, step: int) -> float | None:
    """``eval/<metric>`` of the last evaluation at or before ``step``, if the run reached ``step``."""
    points = points_of(run, metric)
    if points is None:
        return None
    steps, values = points
    if not len(steps) or steps[-1] < step:
        return None
    return float(values[steps <= step][-1])


def _cell(value: float | None) -> str:
    return "" if value is None else f"{value:.2f}"


def table(
    runs: list[TrainingRun], metrics: tuple[str, ...], low: int | None, high: int | None, at: list[int]
) -> str:
    """One row per run: the window's means (when ``low`` or ``high`` is given) and the values at ``at``."""
    labels = run_labels(runs)
    window = low is not None or high is not None
    low, high = low or 0, high if high is not None else 2**62
    shown = f"{low}, {high}" if high < 2**62 else f"{low}, end"
    header = ["run", "seed", *((f"{m} [{shown}]" for m in metrics) if window else ())]
    header += [f"{m} at {step}" for step in at for m in metrics]
    rows = []
    for run in sorted(runs, key=lambda r: (labels[r.path], r.env_name, r.seed, str(r.path))):
        row = [f"{run.env_name} {labels[run.path]}", str(run.seed)]
        row += [_cell(window_mean(run, m, low, high)) for m in metrics] if window else []
        row += [_cell(value_at(run, m, step)) for step in at for m in metrics]
        rows.append(row)
    return markdown(header, rows)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m mcrs_lab.analysis.window", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("paths", nargs="+", type=Path, help="runs, records, or folders of them")
    parser.add_argument("--from", dest="low", type=int, default=None, help="first env step of the window")
    parser.add_argument("--to", dest="high", type=int, default=None, help="last env step of the window")
    parser.add_argument(
        "--at", type=int, action="append", default=[], help="an env step to read (repeatable)"
    )
    parser.add_argument(
        "--metric",
        action="append",
        choices=CHOICES,
        help=f"repeatable (default: {', '.join(METRICS)}); {TARGET_R2}: the reward as r2 for real targets only "
        "would pay it",
    )
    args = parser.parse_args(argv)
    low, high = args.low or 0, args.high if args.high is not None else 2**62
    if low < 0 or high < low:
        raise SystemExit(f"window: error: --from={args.low} --to={args.high}: need 0 <= from <= to")
    if any(step < 0 for step in args.at):
        raise SystemExit(f"window: error: --at={min(args.at)}: must be >= 0")
    try:
        runs = find_runs(args.paths)
    except (RecordError, OSError) as error:
        raise SystemExit(f"window: error: {error}") from None
    for skipped in runs.skipped:
        print(f"skipped {skipped.path}: {skipped.reason}", file=sys.stderr)
    if not runs.training:
        raise SystemExit(f"window: error: no training run or record under {', '.join(map(str, args.paths))}")
    print(table(runs.training, tuple(args.metric or METRICS), args.low, args.high, args.at))
    return 0


if __name__ == "__main__":
    sys.exit(main())
