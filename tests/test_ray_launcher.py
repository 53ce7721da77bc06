"""The distributed path: a two-point ``mcrs-train`` sweep through the Ray launcher config
(``hydra/launcher=ray_cluster``, hydra-ray-launcher) on a local Ray instance, as a user would start it."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.train_helpers import TINY

pytestmark = pytest.mark.slow

STEPS = 80  # two collector batches of 4 x 10-step episodes; evaluations at 0, 40 and 80


def test_a_sweep_runs_through_the_ray_launcher_on_a_local_ray(tmp_path: Path) -> None:
    sweep = tmp_path / "sweep"
    overrides = [o for o in TINY if not o.startswith("train.total_env_steps=")]
    command = [
        sys.executable,
        "-m",
        "mcrs.train",
        "-m",
        "hydra/launcher=ray_cluster",
        # A local Ray of 2 CPUs running both points at once (the config's default asks 2 CPUs a point).
        "+hydra.launcher.ray.init.num_cpus=2",
        "+hydra.launcher.ray.init.include_dashboard=false",
        "hydra.launcher.ray.remote.num_cpus=1",
        f"hydra.sweep.dir={sweep}",
        "algo=qmix",
        "seed=0,1",
        *overrides,
        f"train.total_env_steps={STEPS}",
        "train.eval_interval=40",
    ]
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0", "HYDRA_FULL_ERROR": "0"}
    done = subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    output = done.stdout + done.stderr
    assert done.returncode == 0, output[-3000:]
    assert "Ray Launcher is launching 2 jobs" in output and "Started a local Ray instance" in output
    rewards = {}
    for num, seed in enumerate((0, 1)):
        run = sweep / f"{num}_map10_qmix_seed{seed}"
        assert (run / "checkpoints" / "last.pt").is_file(), sorted(p.name for p in sweep.iterdir())
        with open(run / "logs" / "scalars" / "eval" / "episode_reward.csv", newline="") as f:
            rows = [(int(float(step)), float(value)) for step, value in csv.reader(f)]
        assert [step for step, _ in rows] == [0, 40, STEPS]
        rewards[seed] = rows
        assert f"seed: {seed}" in (run / "config.yaml").read_text()
    assert rewards[0] != rewards[1]  # two seeds, two runs (not one run twice)
