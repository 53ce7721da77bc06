"""Learning curves over seeds against env steps, and the tables read off them (final metrics, rewards at
thirds of the budget, which table 4 is laid out on).

The curves and their figure are the library's (:mod:`mcrs.viz.learning_curves`: IQM over seeds, 95 % stratified
bootstrap band); the tables keep mean ± std over seeds."""

from __future__ import annotations

import numpy as np

from mcrs.viz.learning_curves import Curve, curve_of
from mcrs_lab.analysis.runs import Skipped, TrainingRun

Q_TOT = "train/q_taken_mean"  # mean Q_tot(s, a) of the replayed transitions (figure 8b)


def aggregate(groups: dict[str, list[TrainingRun]], metric: str, skipped: list[Skipped]) -> dict[str, Curve]:
    """Per label, ``metric`` averaged over its runs on the steps they all logged. A run that did not
    log the metric is left out of this metric (and listed in ``skipped``)."""
    curves = {}
    for label, runs in groups.items():
        series = []
        for run in runs:
            found = run.scalar(metric)
            if found is None or len(found[0]) == 0:
                skipped.append(Skipped(run.path, f"no {metric} logged"))
            else:
                series.append(found)
        if not series:
            continue
        curve = curve_of(label, series)
        if curve is None:
            for run in runs:
                skipped.append(Skipped(run.path, f"{label}: its seeds share no step of {metric}"))
            continue
        curves[label] = curve
    return curves


def final_rows(curves_by_metric: dict[str, dict[str, Curve]], order: list[str]) -> list[dict[str, object]]:
    """Per method, every metric's mean and std over seeds at its last common step."""
    rows = []
    for label in order:
        row: dict[str, object] = {"method": label}
        for metric, curves in curves_by_metric.items():
            c = curves.get(label)
            name = metric.split("/")[-1]
            if c is None:
                row[f"{name}_mean"], row[f"{name}_std"] = float("nan"), float("nan")
                continue
            if "seeds" not in row:  # of the first metric (the reward): a run may lack later ones
                row["seeds"], row["env_steps"] = c.seeds, int(c.steps[-1])
            row[f"{name}_mean"], row[f"{name}_std"] = float(c.mean[-1]), float(c.std[-1])
        rows.append(row)
    return rows


def milestone_steps(
    curve: Curve, fractions: tuple[float, ...] = (1 / 3, 2 / 3, 1.0), at: list[int] | None = None
) -> list[int]:
    """The logged steps nearest to fractions of the curve's last step (the paper's 0.67M/1.33M/2M), or
    to the env steps ``at``; a short curve whose nearest step is the same for two of them gives it once
    (no repeated column)."""
    wanted = [f * curve.steps[-1] for f in fractions] if at is None else at
    nearest = [int(curve.steps[np.abs(curve.steps - w).argmin()]) for w in wanted]
    return list(dict.fromkeys(nearest))


def milestone_values(curve: Curve, steps: list[int]) -> list[tuple[float, float]]:
    """(mean, std over seeds) of the curve at each of ``steps``; NaN past the curve's last step (a
    method with a shorter run) by more than half its last evaluation interval (runs of another
    ``num_envs`` evaluate at slightly different steps)."""
    slack = (curve.steps[-1] - curve.steps[-2]) / 2 if len(curve.steps) > 1 else 0
    out = []
    for s in steps:
        if s > curve.steps[-1] + slack:
            out.append((float("nan"), float("nan")))
            continue
        k = int(np.abs(curve.steps - s).argmin())
        out.append((float(curve.mean[k]), float(curve.std[k])))
    return out
