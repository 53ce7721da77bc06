"""Figures 10-12: the end-of-training reward against a swept setting, and the learning curves of a sweep."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mcrs.viz.learning_curves import Curve, plot_curves
from mcrs_lab.analysis.runs import TrainingRun
from mcrs_lab.analysis.sweep_figure import plot_sweep, sweep_panels, sweep_points, sweep_table

BUDGET = 100


def _curve(label: str, values: np.ndarray, last_step: int = BUDGET) -> Curve:
    steps = np.linspace(0, last_step, values.shape[1])
    return Curve(label, steps, values.mean(0), values.std(0), np.zeros(values.shape[1]), values)


def _run(algo: str, delta: float | None) -> TrainingRun:
    algo_config: dict = {"name": algo}
    if delta is not None:
        algo_config["memory"] = {"delta": delta}
    return TrainingRun(Path(f"{algo}_{delta}"), {"algo": algo_config, "seed": 0})


def test_each_point_is_the_seeds_mean_over_the_last_tenth_and_unswept_algorithms_are_left_out() -> None:
    # 11 evaluations at 0, 10, ..., 100: the last tenth is steps 90 and 100.
    ramp = np.tile(np.arange(11.0), (2, 1)) + np.array([[0.0], [2.0]])  # two seeds, 1 apart at the end
    groups = {
        "emc delta=0.0013": [_run("emc", 0.0013)],
        "emc delta=0.13": [_run("emc", 0.13)],
        "semu": [_run("semu", 0.0013)],  # one value of delta: nothing swept
        "qmix": [_run("qmix", None)],  # no memory: no delta
        "cnn_semu delta=0.13": [_run("cnn_semu", 0.13)],
        "cnn_semu delta=0.0013": [_run("cnn_semu", 0.0013)],
    }
    curves = {
        "emc delta=0.0013": _curve("emc delta=0.0013", ramp),
        "emc delta=0.13": _curve("emc delta=0.13", ramp + 5),
        "semu": _curve("semu", ramp),
        "qmix": _curve("qmix", ramp),
        "cnn_semu delta=0.13": _curve("cnn_semu delta=0.13", ramp, last_step=60),  # stopped short
        "cnn_semu delta=0.0013": _curve("cnn_semu delta=0.0013", ramp),
    }
    points = sweep_points(groups, curves, BUDGET, "algo.memory.delta")
    assert [(p.algo, p.value) for p in points] == [("emc", 0.0013), ("emc", 0.13)]
    np.testing.assert_allclose(points[0].seeds, [9.5, 11.5])
    np.testing.assert_allclose(points[1].seeds, [14.5, 16.5])
    table = sweep_table(points, "delta")
    assert "| emc       | 0.0013 |     2 |" in table and "10.50 ± 1.41" in table and "15.50 ± 1.41" in table
    assert sweep_points(groups, curves, BUDGET, "algo.memory_weight") == []


def test_the_figure_is_a_png(tmp_path: Path) -> None:
    groups = {f"emc delta={d}": [_run("emc", d)] for d in (0.00013, 0.0013)}
    curves = {label: _curve(label, np.ones((3, 11))) for label in groups}
    path = plot_sweep(
        sweep_points(groups, curves, BUDGET, "algo.memory.delta"), "delta", tmp_path / "d.png", "t"
    )
    assert path.read_bytes().startswith(b"\x89PNG")


def test_the_learning_curves_of_a_sweep_are_a_panel_per_algorithm_and_a_curve_per_value(
    tmp_path: Path,
) -> None:
    """Figure 12: one colour per value in every panel, so the curves are named by the value alone, unless
    two methods of one algorithm share it (CNN-SEMU at the default delta and at lambda = 0.5)."""
    lambda_half = _run("cnn_semu", 0.0013)
    lambda_half.config["algo"]["memory_weight"] = 0.5
    groups = {
        "emc delta=0.13": [_run("emc", 0.13)],
        "emc delta=0.0013": [_run("emc", 0.0013)],
        "cnn_semu delta=0.0013": [_run("cnn_semu", 0.0013)],
        "cnn_semu lambda=0.5": [lambda_half],
        "cnn_semu delta=0.00013": [_run("cnn_semu", 0.00013)],
        "qmix": [_run("qmix", None)],
    }
    curves = {label: _curve(label, np.ones((3, 11))) for label in groups}
    panels, order = sweep_panels(groups, curves, "algo.memory.delta", "delta", ["cnn_semu", "emc", "semu"])
    assert list(panels) == ["cnn_semu", "emc"]  # in the order asked; semu has no curve
    assert list(panels["emc"]) == ["delta = 0.13", "delta = 0.0013"]
    assert panels["emc"]["delta = 0.13"] is curves["emc delta=0.13"]
    assert list(panels["cnn_semu"]) == ["delta = 0.0013", "cnn_semu lambda=0.5", "delta = 0.00013"]
    assert order == ["delta = 0.00013", "delta = 0.0013", "cnn_semu lambda=0.5", "delta = 0.13"]
    path = plot_curves(panels, tmp_path / "c.png", "t", order, panel_legends=True)
    assert path.read_bytes().startswith(b"\x89PNG")
