"""docs/API.md's Python blocks, run top to bottom in one process as a reader would paste them one after
another: every one runs as written (the build, run, evaluate, plot, callback, algorithm, task, resume and
export sections), and none undoes another (each alone: tests/test_doc_snippets.py)."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

API = Path(__file__).resolve().parents[1] / "docs" / "API.md"


def python_blocks(text: str) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M)


def test_the_api_pages_python_blocks_run_top_to_bottom(tmp_path: Path) -> None:
    blocks = python_blocks(API.read_text())
    assert len(blocks) >= 9, "the page's sections each have a block"
    script = "\n\n".join(blocks)
    ast.parse(script)  # each block is whole Python
    (tmp_path / "api_page.py").write_text(script)
    done = subprocess.run(
        [sys.executable, "api_page.py"], cwd=tmp_path, capture_output=True, text=True, timeout=900
    )
    assert done.returncode == 0, done.stderr[-3000:]
    histories = [line for line in done.stdout.splitlines() if line.startswith("[(0, ")]
    assert len(histories) == 1, done.stdout  # the callback's history
    assert [step for step, _ in ast.literal_eval(histories[0])] == [
        0,
        1600,
        3200,
    ]  # as the page's comment says
    options = (tmp_path / "outputs/bonus_scaled/config.yaml").read_text()
    assert "options:\n    bonus: 0.1\n" in options  # the algorithm's own setting, recorded with the run
    assert (tmp_path / "learning_curve.png").is_file() and (tmp_path / "outputs/exported/agent.pt2").is_file()
