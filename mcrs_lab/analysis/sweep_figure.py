"""Figures 10 and 11: the episode reward at the end of training against a swept setting.

The paper's figure 11 plots, per algorithm, the episode reward at the end of training against delta on a
logarithmic axis; figure 10 does the same for CNN-SEMU's lambda. Each point here is the mean over seeds
of each seed's mean evaluation over the last tenth of the budget (the claims' window), with one dot per
seed, so three overlapping seeds are seen as such.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mcrs.experiment.util.tables import markdown, mean_std
from mcrs.viz.learning_curves import Curve
from mcrs_lab.analysis.claims import window_samples
from mcrs_lab.analysis.runs import TrainingRun

#: The settings a figure is drawn against, with the paper's symbol for the axis.
SWEPT_SETTINGS = {"algo.memory.delta": "delta", "algo.memory_weight": "lambda"}


@dataclass(frozen=True)
class SweepPoint:
    """One algorithm at one value of the swept setting: each finished seed's end-of-training mean."""

    algo: str
    value: float
    seeds: np.ndarray


def sweep_points(
    groups: dict[str, list[TrainingRun]], curves: dict[str, Curve], budget: int, setting: str
) -> list[SweepPoint]:
    """The points of ``setting``'s figure: each method label whose runs set it, seeds that reached the
    budget only. Algorithms with a single value of the setting are left out (nothing is swept)."""
    found: dict[str, list[SweepPoint]] = {}
    for label, runs in groups.items():
        value = runs[0].setting(setting)
        if label not in curves or isinstance(value, bool) or not isinstance(value, (int, float)):
            continue
        samples = window_samples(curves[label], "end", budget)
        if not samples.complete or samples.values.size == 0:
            continue
        found.setdefault(runs[0].algo_name, []).append(
            SweepPoint(runs[0].algo_name, float(value), samples.values)
        )
    points = [
        p for algo_points in found.values() if len({p.value for p in algo_points}) > 1 for p in algo_points
    ]
    return sorted(points, key=lambda p: (p.algo, p.value))


def sweep_panels(
    groups: dict[str, list[TrainingRun]],
    curves: dict[str, Curve],
    setting: str,
    symbol: str,
    algos: list[str],
) -> tuple[dict[str, dict[str, Curve]], list[str]]:
    """The learning curves of a sweep (figure 12): a panel per algorithm of ``algos``, in that order, and a
    curve per value of ``setting`` (``delta = 0.013``; the method's label where two methods of one algorithm
    share a value), and the curves' order: by value, so that a value has one colour in every panel."""
    panels: dict[str, dict[str, Curve]] = {algo: {} for algo in algos}
    values: dict[str, float] = {}
    for label, runs in groups.items():
        algo, value = runs[0].algo_name, runs[0].setting(setting)
        if algo not in panels or label not in curves or not isinstance(value, (int, float)):
            continue
        name = f"{symbol} = {value:g}"
        name = label if name in panels[algo] else name
        panels[algo][name] = curves[label]
        values.setdefault(name, float(value))
    plain = f"{symbol} = "  # at a shared value, the curve named by the value alone comes first
    order = sorted(values, key=lambda n: (values[n], not n.startswith(plain), n))
    return {algo: drawn for algo, drawn in panels.items() if drawn}, order


def sweep_table(points: list[SweepPoint], symbol: str) -> str:
    """Markdown: algorithm, the swept value, seeds, the end-of-training episode reward (mean ± std)."""
    rows = [
        [
            p.algo,
            f"{p.value:g}",
            str(len(p.seeds)),
            mean_std(float(p.seeds.mean()), _std(p.seeds), n=len(p.seeds)),
        ]
        for p in points
    ]
    return markdown(["algorithm", symbol, "seeds", "episode reward, last tenth"], rows)


def _std(values: np.ndarray) -> float:
    return float(values.std(ddof=1)) if len(values) > 1 else 0.0


def plot_sweep(points: list[SweepPoint], symbol: str, path: Path, title: str) -> Path:
    """A line per algorithm through its seeds' mean at each value, the seeds as dots, on a log axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.0, 3.8))
    algos = sorted({p.algo for p in points})
    for k, algo in enumerate(algos):
        colour = plt.cm.tab10(k % 10)
        mine = [p for p in points if p.algo == algo]
        ax.plot(
            [p.value for p in mine], [p.seeds.mean() for p in mine], "o-", color=colour, label=algo, lw=1.4
        )
        for p in mine:
            ax.scatter(np.full(len(p.seeds), p.value), p.seeds, color=colour, s=10, alpha=0.5)
    ax.set_xscale("log")
    ax.set_xlabel(symbol)
    ax.set_ylabel("episode reward, last tenth of training")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
