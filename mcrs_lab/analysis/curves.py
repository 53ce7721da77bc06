"""Learning curves over seeds against env steps, and the tables read off them (final metrics, rewards at
thirds of the budget, the paper's table 4 layout).

The figures draw each method's interquartile mean (IQM) over seeds with a 95 % stratified bootstrap
confidence interval, as rliable and marl-eval do (Agarwal et al., 2021): with 2-5 seeds a Student-t band
is several times the spread of the seeds and fills the panel, the bootstrap interval stays within what the
seeds did. One task per curve, so the strata are the evaluation steps: each is resampled over seeds
(``scipy.stats.bootstrap``, percentile method, a fixed generator so that the figures are reproducible).
The tables keep mean ± std over seeds."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import stats

from mcrs.analysis.runs import Skipped, TrainingRun

#: The four learning-curve panels of figures 6-7, 10 and 11 (greedy evaluation, 32 fixed episodes).
CURVE_METRICS = {
    "eval/episode_reward": "episode reward",
    "eval/uncertainty": "final uncertainty",
    "eval/collisions": "collisions",
    "eval/targets_found": "targets found",
}
#: Every evaluation metric of the final table.
FINAL_METRICS = {
    **CURVE_METRICS,
    "eval/false_discoveries": "false discoveries",
    "eval/no_fly_violations": "no-fly violations",
    "eval/coverage": "coverage",
}
Q_TOT = "train/q_taken_mean"  # mean Q_tot(s, a) of the replayed transitions (figure 8b)


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
    """A policy that does not learn (a heuristic), drawn across a learning-curve panel: its mean over
    evaluation seeds and the 95 % confidence half-width of that mean."""

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
    """The mean of the middle 50 % of ``values`` along ``axis`` (25 % trimmed from each end; rliable's IQM)."""
    return stats.trim_mean(values, 0.25, axis=axis)


def iqm_interval(values: np.ndarray, level: float = 0.95) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IQM over seeds (axis 0 of ``[seeds, steps]``) and its ``level`` bootstrap confidence interval,
    seeds resampled within each step (stratified by step). One seed: the interval is the value itself."""
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
        common = series[0][0]
        for steps, _ in series[1:]:
            common = np.intersect1d(common, steps)
        if len(common) == 0:
            for run in runs:
                skipped.append(Skipped(run.path, f"{label}: its seeds share no step of {metric}"))
            continue
        values = np.stack([vals[np.searchsorted(steps, common)] for steps, vals in series])
        curves[label] = Curve(
            label,
            common,
            values.mean(axis=0),
            values.std(axis=0, ddof=1) if len(series) > 1 else np.zeros(len(common)),
            confidence_half_width(values),
            values,
        )
    return curves


def _legend(fig, handles: list, names: list[str], most: int = 5) -> int:
    """The figure's legend below the panels, in as many columns (up to ``most``) as fit its width: long
    labels (``cnn_semu lambda=0.01 (3 seeds)``) would run off the sides. Returns the column count."""
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
) -> Path:
    """One panel per metric: a line per method (IQM over seeds) with its 95 % bootstrap band, and per panel
    the ``references`` (the heuristics) as horizontal lines, each in its own colour and named at its end."""
    import matplotlib

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
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    handles, names = axes.flat[0].get_legend_handles_labels()
    ncol = _legend(fig, handles, names)
    fig.suptitle(
        title + "  (IQM over seeds, 95 % stratified bootstrap CI; heuristics: mean and 95 % band)",
        fontsize=10,
    )
    fig.tight_layout(rect=(0, 0.06 + 0.02 * ((len(names) - 1) // ncol), 1, 0.96))
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
    """Y limits from the IQMs after the first ``ZOOM_FROM`` of the steps and the reference ``levels``:
    the first evaluations (a reward of -200 on map10 and map20) would otherwise flatten every learning
    curve. Bands may be clipped; a line left out is said in the panel's corner."""
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


def milestone_steps(curve: Curve, fractions: tuple[float, ...] = (1 / 3, 2 / 3, 1.0)) -> list[int]:
    """The logged steps nearest to fractions of the curve's last step (the paper's 0.67M/1.33M/2M); a
    short curve whose nearest step is the same for two fractions gives it once (no repeated column)."""
    last = curve.steps[-1]
    nearest = [int(curve.steps[np.abs(curve.steps - f * last).argmin()]) for f in fractions]
    return list(dict.fromkeys(nearest))


def milestone_values(curve: Curve, steps: list[int]) -> list[tuple[float, float]]:
    """(mean, std over seeds) of the curve at each of ``steps``; NaN past the curve's last step (a
    method with a shorter run)."""
    out = []
    for s in steps:
        if s > curve.steps[-1]:
            out.append((float("nan"), float("nan")))
            continue
        k = int(np.abs(curve.steps - s).argmin())
        out.append((float(curve.mean[k]), float(curve.std[k])))
    return out
