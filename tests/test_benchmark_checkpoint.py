"""``mcrs-bench-checkpoint`` at a tiny size: the incremental checkpoint, the inline one, the verdict."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from mcrs_benchmarks.checkpoint import main

pytestmark = pytest.mark.slow


def test_quick_run_records_its_figures(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "checkpoint.json"
    assert (
        main(["--map", "map10", "--quick", "--new-episodes", "5", "--compare-inline", "--json", str(path)])
        == 0
    )
    figures = json.loads(path.read_text())["figures"]
    value = {name: fig["value"] for name, fig in figures.items()}
    assert value["replay_episodes"] == 16 and value["new_episodes"] == 5
    assert value["first_blocks"] >= 1 and value["incremental_blocks"] == 1  # only the changed block
    for name in ("fill_seconds", "first_seconds", "inline_seconds", "first_gib", "inline_gib", "last_pt_mib"):
        assert value[name] > 0, name
    checkpoint = figures["checkpoint_seconds"]
    assert checkpoint["value"] > 0 and checkpoint["unit"] == "s" and checkpoint["goal"] == "<= 10"
    assert checkpoint["not_judged"] == "map20 without --quick only" and checkpoint["passed"] is None
    out = capsys.readouterr().out
    assert "Experiment.save() with a full replay of 16 episodes" in out
    assert f"full map10 replay (16 episodes): {checkpoint['value']:.2f} s (goal <= 10 s: not judged" in out


def test_bad_arguments_are_rejected_naming_the_argument(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["--new-episodes", "0"])
    assert "--new-episodes must be >= 1, got 0" in capsys.readouterr().err
