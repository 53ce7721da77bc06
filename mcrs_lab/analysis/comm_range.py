"""The communication-range study (paper figure 5): episode metrics against R_c, per policy.

Two sources, both reported when present:
- ``mcrs-eval`` results at several ``env.comm_range`` (a heuristic, or a trained agent evaluated at
  every range): mean over the seeds of each seed's mean over episodes, a trained agent's seeds being
  its training runs (each the mean of its evaluation seeds), a heuristic's its evaluation seeds;
- ``mcrs-train`` runs that differ in ``env.comm_range`` (``experiment=comm_range``): the final
  greedy evaluation, mean over training seeds.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mcrs.env.metrics import METRIC_LABELS
from mcrs.experiment.util.tables import markdown
from mcrs_lab.analysis.pairwise import Comparison, corrected, paired_test
from mcrs_lab.analysis.policy_identity import policy_label
from mcrs_lab.analysis.runs import EvaluationRow

#: The panels of figure 5 (and the reward).
RANGE_METRICS = {name: METRIC_LABELS[name] for name in ("targets_found", "uncertainty", "episode_reward")}
#: Figure 5's statement: as R_c grows, more targets are found and less uncertainty is left.
RANGE_CLAIM = {"targets_found": "higher", "uncertainty": "lower"}


@dataclass(frozen=True)
class RangeCurve:
    """A policy's metrics against R_c: ``mean[metric][k]`` and ``std[metric][k]`` (the spread over seeds,
    sample std; 0 for one seed) at ``ranges[k]`` over ``seeds[k]`` seeds."""

    label: str
    ranges: np.ndarray
    mean: dict[str, np.ndarray]
    std: dict[str, np.ndarray]
    seeds: np.ndarray


def _by_range(rows: list[EvaluationRow]) -> dict[str, dict[float, dict[str, list[EvaluationRow]]]]:
    """Policy label -> R_c -> seed -> its rows: a trained policy's seeds are its training runs, a
    heuristic's its evaluation seeds."""
    grouped: dict[str, dict[float, dict[str, list[EvaluationRow]]]] = {}
    for row in rows:
        unit = str(row.seed) if row.is_heuristic else (row.run or row.policy)
        by_range = grouped.setdefault(row.label or policy_label(row.policy), {})
        by_range.setdefault(row.comm_range, {}).setdefault(unit, []).append(row)
    return grouped


def curves_from_evaluations(rows: list[EvaluationRow]) -> dict[str, RangeCurve]:
    """Per policy label, each metric against R_c. A trained policy's seeds are its training runs, each
    counted by its mean over its evaluation seeds; a heuristic's are the evaluation seeds."""
    return {
        label: _curve(label, {rc: list(units.values()) for rc, units in by_range.items()}, _unit_mean)
        for label, by_range in _by_range(rows).items()
    }


def range_tests(rows: list[EvaluationRow]) -> list[tuple[str, str, Comparison]]:
    """Figure 5's statement tested on each trained policy evaluated at two R_c or more: at its largest R_c
    against its smallest, more targets found and less uncertainty, paired over its training runs (the seeds
    evaluated at both), Holm over every test of the table. (policy, metric, comparison) triples."""
    found: list[tuple[str, str, Comparison]] = []
    for label, by_range in sorted(_by_range([r for r in rows if not r.is_heuristic]).items()):
        if len(by_range) < 2:
            continue
        low, high = min(by_range), max(by_range)
        units = sorted(set(by_range[low]) & set(by_range[high]))
        for metric, better in RANGE_CLAIM.items():
            pairs = [
                (_unit_mean(by_range[high][u], metric), _unit_mean(by_range[low][u], metric)) for u in units
            ]
            pairs = [(h, lo) for h, lo in pairs if h is not None and lo is not None]
            a, b = np.array([h for h, _ in pairs]), np.array([lo for _, lo in pairs])
            found.append((label, metric, paired_test(f"R_c {high:g}", f"R_c {low:g}", a, b, better)))
    tests = corrected([t for _, _, t in found])
    return [(label, metric, t) for (label, metric, _), t in zip(found, tests, strict=True)]


#: What a test of :func:`range_tests` says of the paper's statement.
RANGE_VERDICTS = {
    "holds": "yes",
    "reversed": "**no**: the other way",
    "noise": "within noise",
    "few": "one seed: no test",
}


def range_tests_table(tests: list[tuple[str, str, Comparison]]) -> str:
    """Markdown of :func:`range_tests`: policy, metric, the comparison, and whether it goes the paper's way."""
    rows = [
        [label, f"{METRIC_LABELS[metric]} ({RANGE_CLAIM[metric]})", t.text(), RANGE_VERDICTS[t.outcome]]
        for label, metric, t in tests
    ]
    header = [
        "policy",
        "metric (the paper's direction)",
        "Δ [95 % bootstrap CI], Hedges' g, p → Holm p",
        "as figure 5 says",
    ]
    return markdown(header, rows, left=len(header))


def _unit_mean(unit: list[EvaluationRow], metric: str) -> float | None:
    """One seed's value: the mean of its evaluations (a training run evaluated on several seeds)."""
    values = [v for row in unit if (v := row.means.get(metric)) is not None]
    return float(np.mean(values)) if values else None


def _curve(label: str, by_range: dict, value_of) -> RangeCurve:
    ranges = np.array(sorted(by_range), dtype=np.float64)
    mean, half = {}, {}
    for metric in RANGE_METRICS:
        m, h = [], []
        for r in ranges:
            values = np.array([v for x in by_range[r] if (v := value_of(x, metric)) is not None])
            m.append(values.mean() if len(values) else np.nan)
            h.append(values.std(ddof=1) if len(values) > 1 else 0.0)
        mean[metric], half[metric] = np.array(m), np.array(h)
    seeds = np.array([len(by_range[r]) for r in ranges])
    return RangeCurve(label, ranges, mean, half, seeds)


def curves_from_training(final: dict[tuple[str, float], dict[str, list[float]]]) -> dict[str, RangeCurve]:
    """From ``{(algo, R_c): {metric: [final value per seed]}}`` of training runs."""
    grouped: dict[str, dict[float, list[dict[str, float]]]] = {}
    for (algo, rc), metrics in final.items():
        n = max(len(v) for v in metrics.values())
        per_seed = [{m: v[k] for m, v in metrics.items() if k < len(v)} for k in range(n)]
        grouped.setdefault(f"{algo} (trained at R_c)", {})[rc] = per_seed
    return {label: _curve(label, by_range, lambda x, m: x.get(m)) for label, by_range in grouped.items()}


def plot_range_curves(curves: dict[str, RangeCurve], path: Path, title: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(RANGE_METRICS), figsize=(5.0 * len(RANGE_METRICS), 3.6))
    for ax, (metric, name) in zip(axes, RANGE_METRICS.items(), strict=True):
        for k, (label, c) in enumerate(sorted(curves.items())):
            colour = plt.cm.tab10(k % 10)
            ax.plot(c.ranges, c.mean[metric], "o-", color=colour, label=label, ms=3)
            lo, hi = c.mean[metric] - c.std[metric], c.mean[metric] + c.std[metric]
            ax.fill_between(c.ranges, lo, hi, color=colour, alpha=0.2)
        ax.set_xlabel("communication range R_c (cells)")
        ax.set_title(name)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(title + "  (mean over seeds, band: ± std over seeds)", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
