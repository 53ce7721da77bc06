"""Learning-curve figures: what the legend says each bracketed count is."""

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from mcrs.viz.learning_curves import Curve, Reference, _zoom, plot_curves


def test_legend_says_seeds_for_learners_and_episodes_for_heuristics(tmp_path: Path, monkeypatch) -> None:
    """A learner's count is its training seeds; a heuristic's is what its mean is over (episodes here),
    so a reader does not take 32 evaluation episodes for 32 seeds."""
    kept = []
    monkeypatch.setattr(plt, "close", kept.append)
    values = np.array([[1.0, 2.0], [1.5, 2.5], [0.5, 3.0]])
    curve = Curve("qmix", np.array([0, 10]), values.mean(0), values.std(0), np.zeros(2), values)
    reference = Reference("greedy (heuristic)", 2.0, 0.1, 32, "episodes")
    path = plot_curves(
        {"reward": {"qmix": curve}}, tmp_path / "c.png", "map10", references={"reward": [reference]}
    )
    assert path.is_file()
    (fig,) = kept
    labels = [t.get_text() for legend in fig.legends for t in legend.get_texts()]
    assert labels == ["qmix (3 seeds)", "greedy (heuristic) (32 episodes)"]
    assert "seeds in brackets" not in fig._suptitle.get_text()
    monkeypatch.undo()
    plt.close(fig)


def test_a_legend_of_long_labels_stays_inside_the_figure(tmp_path: Path, monkeypatch) -> None:
    kept = []
    monkeypatch.setattr(plt, "close", kept.append)
    values = np.array([[1.0, 2.0], [1.5, 2.5]])
    labels = [f"cnn_semu lambda={v}" for v in (0.01, 0.05, 0.1, 0.5, 1.0)]
    curves = {
        label: Curve(label, np.array([0, 10]), values.mean(0), values.std(0), np.zeros(2), values)
        for label in labels
    }
    references = [
        Reference(f"{h} (heuristic)", 2.0, 0.1, 3, "evaluation seeds") for h in ("random", "greedy")
    ]
    plot_curves(
        {"reward": curves, "uncertainty": curves}, tmp_path / "c.png", "map10", labels, {"reward": references}
    )
    (fig,) = kept
    (legend,) = fig.legends
    box = legend.get_window_extent(fig.canvas.get_renderer())
    assert box.x0 >= 0 and box.x1 <= fig.bbox.width, (box, fig.bbox.width)
    assert len(legend.get_texts()) == 7 and legend._ncols < 5  # fewer columns than short labels get
    monkeypatch.undo()
    plt.close(fig)


def test_y_limits_ignore_the_untrained_first_evaluations() -> None:
    """A map20 run's evaluation at 10k steps (-250) must not flatten curves that live around 300."""
    steps = np.arange(0, 1_010_000, 10_000)
    mean = np.full(len(steps), 300.0)
    mean[:2] = [-1000.0, -250.0]  # step 0 and 10k: inside the first 5 % of the steps
    curve = Curve("qmix", steps, mean, np.zeros(len(steps)), np.zeros(len(steps)), mean[None])
    fig, ax = plt.subplots()
    _zoom(ax, [curve], [250.0])
    low, high = ax.get_ylim()
    plt.close(fig)
    assert 250.0 > low > 200.0 and 300.0 < high < 310.0  # the reference level and the curve, a margin


def test_iqm_and_its_bootstrap_interval_over_seeds() -> None:
    """The figures' line is the interquartile mean (an outlying seed does not drag it) and the band a
    percentile bootstrap over seeds that stays within what the seeds did (a t band does not)."""
    from mcrs.viz.learning_curves import interquartile_mean, iqm_interval

    values = np.array([[0.0, 1.0], [1.0, 1.0], [2.0, 1.0], [100.0, 1.0]])  # 4 seeds x 2 steps
    assert interquartile_mean(values).tolist() == [1.5, 1.0]  # the middle two seeds
    iqm, low, high = iqm_interval(values)
    assert (low <= iqm).all() and (iqm <= high).all()
    assert low[0] >= 0.0 and high[0] <= 100.0 and low[1] == high[1] == 1.0  # within the seeds' values
    assert iqm_interval(values)[1].tolist() == low.tolist()  # a fixed generator: reproducible figures
    one = iqm_interval(values[:1])
    assert one[0].tolist() == one[1].tolist() == one[2].tolist() == [0.0, 1.0]  # one seed: no interval
