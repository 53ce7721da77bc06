"""``make run``'s path end to end at a tiny size: ``mcrs-train budget=quickstart`` trains CNN-SEMU, evaluates
it and the heuristics, and leaves the metric table, the learning curve and an episode GIF in
``<run dir>/report/``, printing where they are."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from PIL import Image

from mcrs.env.metrics import METRIC_LABELS
from mcrs.policies import POLICIES
from tests.device_helpers import available_devices
from tests.train_helpers import TINY, TINY_MEMORY

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]


def _table_rows(text: str) -> list[list[str]]:
    lines = [line for line in text.splitlines() if line.startswith("|")]
    rows = [[cell.strip() for cell in line.strip("|").split("|")] for line in lines]
    assert re.fullmatch(r"-+:?", rows[1][1]), rows[1]  # the markdown separator row
    return [rows[0], *rows[2:]]


def test_the_makefile_runs_the_quickstart_budget() -> None:
    makefile = (ROOT / "Makefile").read_text()
    assert "$(BIN)/mcrs-train budget=quickstart $(ARGS)" in makefile


@pytest.mark.parametrize("device", available_devices())
def test_quickstart_writes_table_curve_and_gif(device: str, tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    steps = 120
    command = [
        sys.executable, "-m", "mcrs.train", "budget=quickstart", *TINY, *TINY_MEMORY,
        f"train.total_env_steps={steps}", f"train.checkpoint_interval={steps}", "train.eval_interval=40",
        "train.eps_anneal_steps=80", "train.eval_episodes=3", f"hydra.run.dir={run_dir}", f"device={device}",
    ]  # fmt: skip
    env = {**os.environ, "HYDRA_FULL_ERROR": "0"}
    done = subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr

    report = run_dir / "report"
    table, curve, gif = report / "summary.md", report / "learning_curves.png", report / "episode.gif"
    for label, path in (("metric table", table), ("learning curve", curve), ("episode GIF", gif)):
        assert re.search(rf"^  {label} +{re.escape(str(path))}$", done.stdout, re.M), done.stdout

    header, *rows = _table_rows(table.read_text())
    assert header == ["policy", *METRIC_LABELS.values()]
    assert [row[0] for row in rows] == ["cnn_semu (120 steps)", *(f"{p} (heuristic)" for p in POLICIES)]
    for row in rows:
        assert len(row) == len(header)
        for cell in row[1:]:
            mean, std = (float(x) for x in cell.split(" ± "))
            assert std >= 0 and mean == mean  # numbers, not NaN
    with Image.open(curve) as image:
        assert image.format == "PNG" and image.width > 300 and image.height > 200
    with Image.open(gif) as image:
        assert image.format == "GIF" and image.n_frames > 1
    assert "Higher is better for episode reward" in table.read_text()  # the legend says which way is better
    last = done.stdout.strip().splitlines()[-1]
    assert last.startswith("quickstart: a smoke test of the pipeline") and "budget=campaign" in last
    # mcrs-eval's files beside the table, so mcrs-report reads the heuristics of this run too
    assert (report / "metrics.csv").is_file() and (report / "episodes.csv").is_file()
