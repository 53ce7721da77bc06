"""``examples/experiment_api.py`` runs as a script at a tiny size and writes what it promises: a trained,
resumed run directory and its learning curve as a PNG."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from PIL import Image

from mcrs.experiment.run.logging import read_scalar_rows

pytestmark = pytest.mark.slow

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "experiment_api.py"


def test_the_notebook_style_example_builds_runs_evaluates_resumes_and_plots(tmp_path: Path) -> None:
    out = tmp_path / "api"
    done = subprocess.run(
        [sys.executable, str(EXAMPLE)],
        cwd=tmp_path,
        env={**os.environ, "MCRS_EXAMPLE_STEPS": "400", "MCRS_EXAMPLE_OUT": str(out)},
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    lines = done.stdout.splitlines()
    assert lines[0] == "qmix map10 5.0 400"  # the composed, typed config
    assert any(line.startswith("after 400 env steps: greedy episode reward") for line in lines)
    assert any(line.startswith("resumed to 800 env steps") for line in lines)
    run = out / "run"
    assert (run / "checkpoints" / "last.pt").is_file() and (run / "config.yaml").is_file()
    rewards = read_scalar_rows(run / "logs" / "scalars" / "eval" / "episode_reward.csv")
    steps = [step for step, _ in rewards]  # one curve across the resume (evaluate() logs a point too)
    assert steps[0] == 0 and 400 in steps and steps[-1] == 800 and steps == sorted(steps)
    with Image.open(out / "learning_curve.png") as image:
        assert image.format == "PNG" and image.size == (600, 350)
    assert f"learning curve ({len(rewards)} evaluations): {out / 'learning_curve.png'}" in lines
