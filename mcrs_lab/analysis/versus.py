"""Learners against the heuristics (``versus.md|csv`` of ``mcrs-report``): for every learner, heuristic and
evaluation metric, whether the learner ends better, worse or level, and from which env step it is better.

"Ends": each seed's mean over the last tenth of the budget, tested as the claims test a pair
(:func:`mcrs_lab.analysis.pairwise.pairwise_test`, two-sided, at ``ALPHA``, no correction): against the
heuristic's score on the learner's own evaluation episodes where the heuristic played them (one-sample
t-test), else against the heuristic's evaluation seeds (Welch; the cell says "other episodes"). "From which
step": the first evaluation from which the learner's mean over seeds, averaged over the tenth of the budget
before each evaluation (step 0's evaluation, the untrained policy, stands alone), stays better than the
heuristic's score to the end; a learner that crossed back and forth is dated by its last crossing. Which
way is better is the metric's (:data:`mcrs.env.metrics.METRIC_BETTER`). Trained policies evaluated on
fixed episodes (``mcrs-eval``) are judged the same way, each training run one sample, without a date."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from mcrs.env.metrics import METRIC_BETTER, METRIC_LABELS, METRICS
from mcrs.experiment.util.tables import markdown
from mcrs.viz.learning_curves import Curve
from mcrs_lab.analysis.claims import END_FRACTION, window_samples
from mcrs_lab.analysis.evaluations import (
    Layout,
    heuristic_layout_values,
    heuristic_samples,
    trained_layouts,
    trained_samples,
)
from mcrs_lab.analysis.pairwise import Samples, pairwise_test
from mcrs_lab.analysis.runs import EvaluationRow
from mcrs_lab.analysis.step_notation import format_steps

#: compare()'s outcomes as the table words them (the learner is the first of the pair).
OUTCOME_WORDS = {"holds": "better", "reversed": "worse", "noise": "level", "few": "one seed"}


@dataclass(frozen=True)
class Versus:
    """One learner against one heuristic on one metric."""

    method: str
    heuristic: str
    metric: str
    outcome: str  # better | worse | level | one seed | unfinished
    p: float  # the test's two-sided p-value (NaN when not tested)
    method_mean: float
    heuristic_mean: float  # its score on the learner's episodes, or its mean over its evaluation seeds
    since: int | None = None  # env step from which the learner stays better (only when it ends better)
    test: str = "none"  # one-sample (the learner's episodes) | welch (other episodes) | none

    def text(self) -> str:
        if self.outcome == "unfinished":
            return "not run to the end"
        if self.outcome == "one seed":
            return "one seed"
        word = f"**{self.outcome}**" if self.outcome == "better" else self.outcome
        since = "" if self.since is None else f" from {format_steps(self.since)}"
        other = ", other episodes" if self.test == "welch" else ""
        return f"{word} (p = {self.p:.3f}{other}){since}"


def better_since(curve: Curve, target: float, better: str, window: float) -> int | None:
    """The first env step from which ``curve``'s mean over seeds, averaged over the ``window`` env steps
    up to each evaluation, stays better than ``target``; None when it does not end better."""
    first = np.searchsorted(curve.steps, curve.steps - window, side="right")
    if curve.steps[0] == 0:  # the untrained policy's evaluation dates nothing after it
        first[1:] = np.maximum(first[1:], 1)
    total = np.concatenate([[0.0], np.cumsum(curve.mean)])
    last = np.arange(1, len(curve.steps) + 1)
    smoothed = (total[last] - total[first]) / (last - first)
    ahead = smoothed > target if better == "higher" else smoothed < target
    if not ahead[-1]:
        return None
    behind = np.flatnonzero(~ahead)
    return int(curve.steps[behind[-1] + 1 if len(behind) else 0])


def versus(
    curves: dict[str, dict[str, Curve]],
    order: list[str],
    evaluations: list[EvaluationRow],
    comm_range: float | None,
    budget: int,
    layouts: dict[str, frozenset[Layout]] | None = None,
) -> list[Versus]:
    """Every learner of ``order`` against every heuristic evaluated at ``comm_range``, on every metric both
    have (``curves``: ``eval/<metric>`` -> label -> curve), metric by metric in METRICS' order.
    ``layouts``: per label, the episodes its periodic evaluations played (empty or absent: unknown)."""
    out = []
    for metric in METRICS:
        by_label = curves.get(f"eval/{metric}", {})
        heuristics = _heuristics(evaluations, comm_range, metric)
        for label in (label for label in order if label in by_label):
            curve = by_label[label]
            ours = replace(
                window_samples(curve, "end", budget), layouts=(layouts or {}).get(label, frozenset())
            )
            out += _against(label, ours, metric, heuristics, curve, END_FRACTION * budget)
    return out


def versus_evaluated(evaluations: list[EvaluationRow]) -> list[Versus]:
    """Every trained policy evaluated on fixed episodes (each training run one sample: its mean over the
    evaluation seeds) against every heuristic evaluated with it, on every metric; no date (no curve)."""
    out = []
    layouts = trained_layouts(evaluations)
    for metric in METRICS:
        heuristics = _heuristics(evaluations, None, metric)
        for label, values in trained_samples(evaluations, metric).items():
            ours = Samples(label, values, layouts=layouts.get(label, frozenset()))
            out += _against(label, ours, metric, heuristics)
    return out


def _heuristics(evaluations: list[EvaluationRow], comm_range: float | None, metric: str) -> list[Samples]:
    """Each heuristic's evaluation seeds and its score on every layout it played."""
    on_layouts = heuristic_layout_values(evaluations, comm_range, metric)
    return [
        Samples(name, values, on_layouts=on_layouts.get(name, ()), heuristic=True)
        for name, values in heuristic_samples(evaluations, comm_range, metric).items()
    ]


def _against(
    label: str,
    ours: Samples,
    metric: str,
    heuristics: list[Samples],
    curve: Curve | None = None,
    window: float = 0.0,
) -> list[Versus]:
    """Learner ``label``'s samples on ``metric`` against each heuristic's; dated on ``curve`` where it ends
    better."""
    better = METRIC_BETTER[metric]
    out = []
    for heuristic in heuristics:
        if not len(heuristic.values):
            continue
        if not ours.complete or not len(ours.values):
            out.append(
                Versus(label, heuristic.label, metric, "unfinished", math.nan, math.nan, heuristic.mean)
            )
            continue
        result = pairwise_test(ours, heuristic, better)
        target = result.score if result.test == "one-sample" else heuristic.mean
        since = better_since(curve, target, better, window) if result.outcome == "holds" and curve else None
        word = OUTCOME_WORDS[result.outcome]
        out.append(
            Versus(label, heuristic.label, metric, word, result.p, ours.mean, target, since, result.test)
        )
    return out


def versus_table(results: list[Versus]) -> tuple[list[dict[str, object]], str]:
    """versus.csv's rows and versus.md: a row per (metric, learner), a column per heuristic."""
    heuristics = list(dict.fromkeys(r.heuristic for r in results))
    cells: dict[tuple[str, str], dict[str, str]] = {}
    for r in results:
        cells.setdefault((r.metric, r.method), {})[r.heuristic] = r.text()
    rows = [
        [METRIC_LABELS[metric], method, *(found.get(h, "-") for h in heuristics)]
        for (metric, method), found in cells.items()
    ]
    csv_rows = [
        {
            "metric": r.metric,
            "method": r.method,
            "heuristic": r.heuristic,
            "outcome": r.outcome,
            "p": r.p,
            "method_mean": r.method_mean,
            "heuristic_mean": r.heuristic_mean,
            "since": r.since if r.since is not None else "",
            "test": r.test,
        }
        for r in results
    ]
    header = ["metric", "method", *(h.removesuffix(" (heuristic)") for h in heuristics)]
    return csv_rows, markdown(header, rows, left=len(header))
