"""The whole-run overhead benchmark runs both algorithms' real trainers and records its projection."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from mcrs_benchmarks.loop import LoopResult
from mcrs_benchmarks.overhead import main, project

from tests.bench_helpers import run_json

pytestmark = pytest.mark.slow

QUICK = ["--map", "map10", "--quick", "--loop-steps", "1", "--entries", "500", "--threads", "1"]


def _run(tmp_path: Path, argv: list[str]) -> dict[str, Any]:
    return run_json(main, tmp_path / "overhead.json", argv)


def test_quick_run_records_both_algorithms_and_the_ratio(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = _run(tmp_path, QUICK)
    figures = data["figures"]
    rows = {row["algo"]: row for row in data["tables"]["algorithms"]}
    assert set(rows) == {"qmix", "cnn_semu"}
    for algo, row in rows.items():
        assert row["env_steps_per_s"] > 0 and row["hours"] >= row["hours_window_eval"] > 0
        assert figures[f"{algo}.hours"]["value"] == row["hours"]
    assert rows["qmix"]["hours_growth"] == 0.0 and rows["cnn_semu"]["hours_growth"] > 0  # the growth term
    assert figures["reembed_us_per_state"]["value"] > 0 and figures["insert_ms"]["value"] > 0
    ratio = figures["ratio"]
    assert ratio["value"] == pytest.approx(rows["cnn_semu"]["hours"] / rows["qmix"]["hours"])
    assert ratio["goal"] == "<= 1.3" and ratio["not_judged"] == "map20 without --quick only"
    out = capsys.readouterr().out
    assert "re-embedding probe: 500 states" in out
    assert f"whole 2M run {ratio['value']:.2f}x (goal <= 1.3x: not judged" in out
    assert f"CNN_SEMU vs QMIX: {ratio['value']:.2f}x (whole run, map10, load average" in out


def test_projection_adds_the_growth_of_re_embedding_with_the_buffer() -> None:
    loop = LoopResult("map20", 10_000, 10.0, 100, 5.0, 0.0, 32, 10_000, 20_000, 12.0)
    base = loop.hours(2_000_000, True)
    # 1 us per state, t_emb 10k, capacity 1M: trainings k = 1..200 re-embed min(10k k, 1M) - 10k states.
    hours, extra = project(loop, 1e-6, 0.0, 10_000, 1_000_000, 3_200)
    expected = sum(1e-6 * max(0, min(10_000 * k, 1_000_000) - 10_000) for k in range(1, 201)) / 3600
    assert extra == pytest.approx(expected) and hours == pytest.approx(base + expected)
    _, with_inserts = project(loop, 0.0, 0.032, 10_000, 1_000_000, 3_200)
    assert with_inserts == pytest.approx(0.032 * (2_000_000 - 20_000) / 3_200 / 3600)


def test_emc_run_records_its_ratio_to_qmix_against_its_own_goal(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = _run(tmp_path, [*QUICK, "--algo", "emc"])
    assert {row["algo"] for row in data["tables"]["algorithms"]} == {"qmix", "emc"}
    ratio = data["figures"]["ratio"]
    assert ratio["value"] > 0 and ratio["goal"] == "<= 2" and ratio["passed"] is None
    out = capsys.readouterr().out  # the line docs and issues quote
    assert f"EMC vs QMIX: {ratio['value']:.2f}x (whole run, map10, load average" in out


def test_bad_arguments_are_rejected_naming_the_argument(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["--entries", "0"])
    assert "--entries must be >= 1, got 0" in capsys.readouterr().err
