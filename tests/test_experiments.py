"""A smoke run of every section-6 preset (conf/experiment/ at budget=smoke), then mcrs-report over it.

Each preset runs as the user runs it (``mcrs-train experiment=<name> budget=smoke``, a Hydra multirun in
a subprocess), with every sweep point, so a preset that does not compose or crashes fails here.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from mcrs.policies import POLICIES
from mcrs_lab.analysis.report import main as report_main
from tests.test_report import read_csv

pytestmark = pytest.mark.slow

#: Preset -> (the run directories it must make, the methods its report must show).
PRESETS = {
    "baselines": (
        21,
        ["qmix", "vdn", "qplex", "emc", "emu", "semu", "cnn_semu"],
    ),
    "emu_comparison": (5, ["qmix", "emu", "emu_370", "emu_change", "cnn_semu"]),
    "comm_range": (11, [f"qmix R_c={rc}" for rc in range(11)]),
    "lambda": (5, [f"cnn_semu lambda={w:g}" for w in (0.01, 0.05, 0.1, 0.5, 1.0)]),
    "delta": (
        12,
        [
            f"{algo} delta={d:g}"
            for algo in ("emc", "semu", "cnn_semu")
            for d in (1.3e-4, 1.3e-3, 1.3e-2, 1.3e-1)
        ],
    ),
    "shield": (2, ["qmix", "cnn_semu"]),
    "shields": (2, ["qmix", "cnn_semu"]),
    "shields_scaled": (2, ["qmix", "cnn_semu"]),
    "shields_pymarl2": (2, ["qmix", "cnn_semu"]),
    "shields_gamma": (3, ["qmix gamma=0.5", "qmix gamma=0.9", "qmix gamma=0.95"]),
    "gamma": (2, ["qmix gamma=0.5", "qmix gamma=0.9"]),
    "shields_view": (1, ["qmix"]),
}
#: Preset -> the scenario's shields (no_fly_shield, uav_shield) in its runs.
SHIELDS = {
    "shield": (True, False),
    "shields": (True, True),
    "shields_scaled": (True, True),
    "shields_pymarl2": (True, True),
    "shields_gamma": (True, True),
    "shields_view": (True, True),
}
#: Preset -> its env.far_view (0, the paper's observation, elsewhere).
FAR_VIEW = {"shields_view": 3}
#: Preset -> its algo.reward_scale (1 elsewhere).
REWARD_SCALE = {"shields_scaled": 0.05}


def run_preset(name: str, sweep_dir: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "mcrs.train",
            f"experiment={name}",
            "budget=smoke",
            f"hydra.sweep.dir={sweep_dir}",
        ],
        cwd=sweep_dir.parent,
        env={**os.environ, "HYDRA_FULL_ERROR": "0"},
        capture_output=True,
        text=True,
        timeout=600,
    )


@pytest.fixture(scope="module")
def baselines(tmp_path_factory: pytest.TempPathFactory) -> Path:
    sweep = tmp_path_factory.mktemp("baselines") / "sweep"
    done = run_preset("baselines", sweep)
    assert done.returncode == 0, done.stderr[-3000:]
    return sweep


@pytest.mark.parametrize("name", list(PRESETS))
def test_preset_smoke_run_and_report(name: str, tmp_path: Path, baselines: Path) -> None:
    expected_runs, methods = PRESETS[name]
    if name == "baselines":
        sweep = baselines
    else:
        sweep = tmp_path / "sweep"
        done = run_preset(name, sweep)
        assert done.returncode == 0, done.stderr[-3000:]
    runs = sorted(p for p in sweep.iterdir() if (p / "config.yaml").is_file())
    assert len(runs) == expected_runs
    for run in runs:
        config = OmegaConf.load(run / "config.yaml")
        assert (config.experiment, config.budget, config.train.total_env_steps) == (name, "smoke", 200)
        assert (config.env.no_fly_shield, config.env.uav_shield) == SHIELDS.get(name, (False, False))
        assert config.algo.reward_scale == REWARD_SCALE.get(name, 1.0)
        assert config.env.far_view == FAR_VIEW.get(name, 0)
        assert config.preset == ("pymarl2" if name == "shields_pymarl2" else "pymarl")
        assert (run / "checkpoints" / "last.pt").is_file()
    maps = sorted({OmegaConf.load(r / "config.yaml").env.name for r in runs})
    out = tmp_path / "report"
    assert report_main([str(sweep), "--out", str(out), "--env", maps[-1]]) == 0
    shown = [r["method"] for r in read_csv(out / "final.csv")]
    if name == "baselines":  # one map at a time: the other two are skipped with the reason
        assert shown == methods
        assert "map map10, the report is on map20" in (out / "report.md").read_text()
    else:
        assert sorted(shown) == sorted(methods)
    assert (out / "learning_curves.png").is_file()
    # table 4 where delta was swept, and on the paper's map (20 x 20) wherever a memory method ran
    configs = [OmegaConf.load(r / "config.yaml") for r in runs]
    memory = any(c.algo.memory.enabled for c in configs if c.env.name == maps[-1])
    assert (out / "table4.md").exists() == (name == "delta" or (maps[-1] == "map20" and memory))
    assert (out / "comm_range.md").exists() == (name == "comm_range")


def test_tsne_from_a_saved_buffer(baselines: Path, tmp_path: Path) -> None:
    out = tmp_path / "tsne"
    report_main([str(baselines), "--out", str(out), "--env", "map10", "--tsne", "--tsne-samples", "120"])
    text = (out / "tsne.md").read_text()
    assert "drawn from the saved D_E of" in text and "map10_cnn_semu_seed0" in text
    for panel in ("raw state", "random projection (EMC)", "SEMU keys (FC)", "CNN-SEMU keys"):
        assert f"| {panel}" in text
    assert (out / "tsne.png").stat().st_size > 10_000


@pytest.mark.parametrize(
    ("study", "expected"), [("comm_range", 11), ("heuristics", len(POLICIES))]
)  # every registered heuristic
def test_evaluation_study_smoke_and_report(study: str, expected: int, tmp_path: Path) -> None:
    sweep = tmp_path / "sweep"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "mcrs.evaluate",
            f"study={study}",
            "seed=0",
            "episodes=2",
            "env.max_steps=5",
            f"hydra.sweep.dir={sweep}",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    out = tmp_path / "report"
    assert report_main([str(sweep), "--out", str(out)]) == 0
    if study == "comm_range":  # one point per range of the greedy heuristic
        rows = read_csv(out / "comm_range.csv")
        assert [float(r["comm_range"]) for r in rows] == list(range(11))
        assert {r["policy"] for r in rows} == {"greedy (evaluated at R_c)"}
    else:  # the three heuristics, one evaluation seed each
        assert "| greedy (heuristic)    |     1 |" in (out / "report.md").read_text()
        assert len(list(sweep.glob("*/metrics.csv"))) == 1
        assert expected == len(read_csv(next(sweep.glob("*/metrics.csv"))))


@pytest.mark.parametrize(
    ("extra", "expected"), [([], "n_jobs: 2"), (["hydra/launcher=basic"], "BasicLauncher")]
)
def test_cpu_budget_uses_two_local_processes_unless_another_launcher_is_named(
    extra: list[str], expected: str, tmp_path: Path
) -> None:
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "mcrs.train",
            "experiment=lambda",
            "budget=cpu",
            *extra,
            "--cfg",
            "hydra",
            "-p",
            "hydra.launcher",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert expected in done.stdout
