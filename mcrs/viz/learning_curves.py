"""Learning curves against env steps: one method's metric over seeds (:class:`Curve`) and the figure of them
(:func:`plot_curves`).

``mcrs-train budget=quickstart`` draws its run's report with them, and ``mcrs-report`` (mcrs_lab.analysis)
draws the paper's figures 6-7, 10 and 11. Each method is drawn as its interquartile mean (IQM) over seeds
with a 95 % stratified bootstrap interval, as rliable and marl-eval do (Agarwal et al., 2021); with 2-5
seeds a Student-t band would fill the panel. The strata are the evaluation steps, each resampled over seeds
with ``scipy.stats.bootstrap`` (percentile method, fixed generator)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import stats

from mcrs.env.metrics import METRIC_LABELS, METRICS

#: The four learning-curve panels of figures 6-7, 10 and 11 (greedy evaluation, 32 fixed episodes).
CURVE_METRICS = {
    f"eval/{name}": METRIC_LABELS[name]
    for name in ("episode_reward", "uncertainty", "collisions", "targets_found")
}
#: Every evaluation metric of the final table.
FINAL_METRICS = {**CURVE_METRICS, **{f"eval/{name}": METRIC_LABELS[name] for name in METRICS}}


@dataclass(frozen=True)
class Curve:
    """One method's metric over seeds, on the env steps that every seed logged."""

    label: str
    steps: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    half_width: np.ndarray  # 95 % confidence half-width of the mean (Student t; 0 for one seed)
    values: np.ndarray  # [seeds, steps]
    iqm: np.ndarray = field(init=False)  # interquartile mean over seeds (the figures' line)
    ci_low: np.ndarray = field(init=False)  # 95 % bootstrap confidence interval of the IQM (the band)
    ci_high: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        for name, value in zip(("iqm", "ci_low", "ci_high"), iqm_interval(self.values), strict=True):
            object.__setattr__(self, name, value)  # frozen: set once, from the seeds' values

    @property
    def seeds(self) -> int:
        return self.values.shape[0]


@dataclass(frozen=True)
class Reference:
    """A heuristic drawn across a panel: its mean over evaluation seeds and the 95 % confidence half-width of
    that mean."""

    label: str
    mean: float
    half_width: float
    count: int
    over: str  # what ``count`` counts: "episodes" or "evaluation seeds"


def confidence_half_width(values: np.ndarray, level: float = 0.95) -> np.ndarray:
    """Half-width of the ``level`` confidence interval of the mean over axis 0 (Student t)."""
    n = values.shape[0]
    if n < 2:
        return np.zeros(values.shape[1:])
    sem = values.std(axis=0, ddof=1) / np.sqrt(n)
    return stats.t.ppf(0.5 + level / 2, n - 1) * sem


BOOTSTRAP_RESAMPLES = 2000
BOOTSTRAP_SEED = 0


def interquartile_mean(values: np.ndarray, axis: int = 0) -> np.ndarray:
    """Return the mean of the middle 50 % of ``values`` along ``axis`` (rliable's IQM)."""
    return stats.trim_mean(values, 0.25, axis=axis)


def iqm_interval(values: np.ndarray, level: float = 0.95) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return the IQM over seeds of ``[seeds, steps]`` and its ``level`` bootstrap interval, stratified by
    step. With one seed the interval is the value itself."""
    iqm = interquartile_mean(values)
    if values.shape[0] < 2:
        return iqm, iqm.copy(), iqm.copy()
    result = stats.bootstrap(
        (values,),
        interquartile_mean,
        axis=0,
        vectorized=True,
        n_resamples=BOOTSTRAP_RESAMPLES,
        confidence_level=level,
        method="percentile",
        random_state=np.random.default_rng(BOOTSTRAP_SEED),
    )
    low, high = result.confidence_interval
    return iqm, np.minimum(low, iqm), np.maximum(high, iqm)


def curve_of(label: str, series: list[tuple[np.ndarray, np.ndarray]]) -> Curve | None:
    """Return one method's curve on the steps every seed logged, or None when they share no step."""
    common = series[0][0]
    for steps, _ in series[1:]:
        common = np.intersect1d(common, steps)
    if len(common) == 0:
        return None
    values = np.stack([vals[np.searchsorted(steps, common)] for steps, vals in series])
    return Curve(
        label,
        common,
        values.mean(axis=0),
        values.std(axis=0, ddof=1) if len(series) > 1 else np.zeros(len(common)),
        confidence_half_width(values),
        values,
    )


def _legend(fig, handles: list, names: list[str], most: int = 5) -> int:
    """Draw the legend below the panels in as many columns as fit, at most ``most``; return the column count."""
    renderer = fig.canvas.get_renderer()
    for ncol in range(min(len(names), most), 0, -1):
        legend = fig.legend(handles, names, loc="lower center", ncol=ncol, fontsize=8, frameon=False)
        if ncol == 1 or legend.get_window_extent(renderer).width <= 0.98 * fig.bbox.width:
            return ncol
        legend.remove()
    return 1


def plot_curves(
    panels: dict[str, dict[str, Curve]],
    path: Path,
    title: str,
    order: list[str] | None = None,
    references: dict[str, list[Reference]] | None = None,
    panel_legends: bool = False,
) -> Path:
    """Draw one panel per metric: each method's IQM line and 95 % band, and the ``references`` as named
    horizontal lines. One legend below the panels names what the first panel draws; with ``panel_legends``
    each panel has its own (panels whose curves differ, as one panel per algorithm of a sweep)."""
    import matplotlib  # deferred: an optional, heavy dependency, needed only to draw

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(panels)
    cols = 2 if n > 1 else 1
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(6.0 * cols, 3.8 * rows), squeeze=False)
    labels = order or sorted({label for curves in panels.values() for label in curves})
    colours = {label: plt.cm.tab10(k % 10) for k, label in enumerate(labels)}
    for ax, (name, curves) in zip(axes.flat, panels.items(), strict=False):
        for label in labels:
            if label not in curves:
                continue
            c = curves[label]
            ax.plot(
                c.steps, c.iqm, color=colours[label], label=f"{label} ({_count(c.seeds, 'seed')})", lw=1.4
            )
            ax.fill_between(c.steps, c.ci_low, c.ci_high, color=colours[label], alpha=0.18, lw=0)
        lines = (references or {}).get(name, [])
        for k, ref in enumerate(lines):
            colour = HEURISTIC_COLOURS[k % len(HEURISTIC_COLOURS)]  # apart from the methods' tab10
            style = ("--", ":", "-.")[k % 3]
            ax.axhline(
                ref.mean, color=colour, ls=style, lw=1.3, label=f"{ref.label} ({ref.count} {ref.over})"
            )
            ax.axhspan(ref.mean - ref.half_width, ref.mean + ref.half_width, color=colour, alpha=0.08, lw=0)
            ax.annotate(ref.label.split(" (")[0], (1.0, ref.mean), xycoords=("axes fraction", "data"),
                        xytext=(-3, 2), textcoords="offset points", ha="right", va="bottom", fontsize=7,
                        color=colour)  # fmt: skip
        _zoom(ax, [curves[label] for label in labels if label in curves], [r.mean for r in lines])
        ax.set_title(name)
        ax.set_xlabel("env steps")
        ax.grid(alpha=0.3)
        if panel_legends:
            ax.legend(fontsize=7, loc="lower right")
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    bottom = 0.0
    if not panel_legends:
        handles, names = axes.flat[0].get_legend_handles_labels()
        ncol = _legend(fig, handles, names)
        bottom = 0.06 + 0.02 * ((len(names) - 1) // ncol)
    drawn = "IQM over seeds, 95 % stratified bootstrap CI" + (
        "; heuristics: mean and 95 % band" if any((references or {}).get(name) for name in panels) else ""
    )
    one_column = cols == 1  # too narrow for the title and what is drawn on one line
    fig.suptitle(f"{title}\n({drawn})" if one_column else f"{title}  ({drawn})", fontsize=10)
    fig.tight_layout(rect=(0, bottom, 1, 0.92 if one_column else 0.96))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


#: The heuristics' lines: black, then the tab10 colours that the first eight methods do not take.
HEURISTIC_COLOURS = ("black", "#17becf", "#bcbd22", "#7f7f7f")


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}{'' if n == 1 else 's'}"


ZOOM_FROM = 0.05  # the y limits ignore the first 5 % of the steps (the untrained policy's evaluations)


def _zoom(ax, curves: list[Curve], levels: list[float] | None = None) -> None:
    """Return y limits from the IQMs after the first ``ZOOM_FROM`` of the steps and the reference ``levels``.
    Otherwise the first evaluations (-200 on map10 and map20) would flatten every curve. A line left out is
    noted in the panel's corner."""
    last = max((int(c.steps[-1]) for c in curves), default=0)
    later = [c.iqm[c.steps > ZOOM_FROM * last] for c in curves if (c.steps > ZOOM_FROM * last).any()]
    if not later:
        return
    later += [np.array(levels)] if levels else []
    lo, hi = min(v.min() for v in later), max(v.max() for v in later)
    margin = 0.1 * (hi - lo) or 1.0
    ax.set_ylim(lo - margin, hi + margin)
    every = np.concatenate([c.iqm for c in curves])
    outside = every[(every < lo - margin) | (every > hi + margin)]
    if outside.size:  # say what the zoom leaves out (the untrained policy's first evaluations)
        ax.text(0.01, 0.02 if outside.min() < lo else 0.98, f"zoomed: first evaluations reach {_short(outside)}",
                transform=ax.transAxes, fontsize=7, color="dimgray", va="bottom" if outside.min() < lo else "top")  # fmt: skip


def _short(outside: np.ndarray) -> str:
    extreme = outside.min() if abs(outside.min()) >= abs(outside.max()) else outside.max()
    return f"{extreme:.3g}"
