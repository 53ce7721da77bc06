"""The benchmark harness: verdicts from goals, the JSON every command writes, the shared arguments."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import pytest
import torch
from mcrs_benchmarks.harness import SCHEMA, Figure, Goal, Report, make_parser, run_benchmark


@pytest.mark.parametrize(
    ("op", "value", "met"),
    [("<=", 1.15, True), ("<=", 1.16, False), ("<", 5.0, False), ("<", 4.9, True), (">=", 100, True),
     (">=", 99.9, False), (">", 0.0, False)],
)  # fmt: skip
def test_goal_compares_with_its_operator(op: str, value: float, met: bool) -> None:
    limit = {"<=": 1.15, "<": 5.0, ">=": 100.0, ">": 0.0}[op]
    assert Goal(op, limit).met(value) is met


def test_a_goal_with_an_unknown_operator_is_refused_in_one_line() -> None:
    with pytest.raises(ValueError, match=r"Goal op must be one of \['<', '<=', '>', '>='\], got '=='"):
        Goal("==", 1.0)


def test_figure_verdicts() -> None:
    goal = Goal("<=", 10.0)
    assert Figure("a", 9.0, "s", goal).verdict == "PASS"
    assert Figure("a", 11.0, "s", goal).verdict == "FAIL"
    assert Figure("a", 11.0, "s", goal, not_judged="--quick").verdict == "not judged (--quick)"
    assert Figure("a", 11.0, "s", goal, not_judged="--quick").passed is None
    assert Figure("a", 1.0, "s", goal, valid=False).passed is False  # a void comparison never passes
    assert Figure("a", None, "s", goal).passed is False  # a judged figure that is missing fails
    assert Figure("a", math.nan, "s", goal).passed is False
    assert Figure("a", 1.0, "s").passed is None and Figure("a", 1.0, "s").verdict == "n/a"


def _body(args: argparse.Namespace, report: Report) -> None:
    report.header("test benchmark")
    report.figure("good", 1.0, "s", Goal("<=", 2.0))
    report.figure("quick", 3.0, "s", Goal("<=", 2.0), not_judged="--quick")
    report.figure("nan", math.nan, "ms")
    report.row("rows", n=1, seconds=0.5)
    report.row("rows", n=2, seconds=0.25)


def _parser() -> argparse.ArgumentParser:
    parser = make_parser("mcrs-bench-test", "a test", threads=1, quick="smoke test")
    parser.add_argument("--size", type=int, default=3)
    return parser


def test_run_writes_the_report_as_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    threads = torch.get_num_threads()
    path = tmp_path / "sub" / "result.json"
    assert run_benchmark(_parser(), ["--threads", "1", "--json", str(path), "--size", "5"], _body) == 0
    assert torch.get_num_threads() == threads
    out = capsys.readouterr().out
    assert out.startswith("MCRS test benchmark: device=cpu, torch threads=1, cpus=")
    assert f"command: mcrs-bench-test --threads 1 --json {path} --size 5" in out
    assert out.rstrip().endswith(f"results as JSON: {path}")
    data = json.loads(path.read_text())
    assert data["schema"] == SCHEMA and data["benchmark"] == "mcrs-bench-test"
    assert data["arguments"] == {"threads": 1, "quick": False, "size": 5}
    assert data["machine"]["torch_threads"] == 1 and data["machine"]["torch"] == torch.__version__
    assert len(data["machine"]["load_average"]) == 3 and len(data["machine"]["load_average_after"]) == 3
    figures = data["figures"]
    assert figures["good"] == {"value": 1.0, "unit": "s", "goal": "<= 2", "passed": True, "not_judged": None,
                               "valid": True, "note": None}  # fmt: skip
    assert figures["quick"]["passed"] is None and figures["quick"]["not_judged"] == "--quick"
    assert figures["nan"]["value"] is None  # JSON has no NaN
    assert data["passed"] is True  # only judged figures count
    assert data["tables"]["rows"] == [{"n": 1, "seconds": 0.5}, {"n": 2, "seconds": 0.25}]


def test_default_json_goes_under_outputs_benchmarks_and_none_writes_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    run_benchmark(_parser(), [], _body)
    written = list((tmp_path / "outputs" / "benchmarks").glob("mcrs-bench-test-*.json"))
    assert len(written) == 1 and json.loads(written[0].read_text())["benchmark"] == "mcrs-bench-test"
    run_benchmark(_parser(), ["--json", "none"], _body)
    assert len(list(tmp_path.rglob("*.json"))) == 1
    assert "results as JSON" not in capsys.readouterr().out.split("command: mcrs-bench-test --json none")[1]


def test_bad_threads_are_refused_naming_the_argument(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        run_benchmark(_parser(), ["--threads", "-1"], _body)
    assert "--threads must be >= 0, got -1" in capsys.readouterr().err


def test_a_failed_figure_fails_the_report() -> None:
    report = Report("b", "b", {})
    report.figure("ok", 1.0, goal=Goal(">=", 1.0))
    assert report.passed is True
    report.figure("missing", None, goal=Goal(">=", 1.0))
    assert report.passed is False
    assert Report("b", "b", {}).passed is None  # nothing judged
