"""Learning-curve figures: what the legend says each bracketed count is."""

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from mcrs.analysis.curves import Curve, Reference, plot_curves


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
