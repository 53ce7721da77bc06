"""The whole-run overhead benchmark runs both algorithms' real trainers and prints its projection."""

from __future__ import annotations

import re

import pytest

from mcrs.benchmarks.learner import LoopResult
from mcrs.benchmarks.overhead import main, project


def test_quick_run_prints_both_algorithms_and_the_ratio(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--map", "map10", "--quick", "--loop-steps", "1", "--entries", "500", "--threads", "1"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"^qmix\s+[\d,]+\s+[\d.]+", out, re.M)
    assert re.search(r"^cnn_semu\s+[\d,]+\s+[\d.]+", out, re.M)
    assert re.search(r"re-embedding probe: 500 states, [\d.]+ us/state", out)
    assert re.search(
        r"ratio cnn_semu / qmix: window [\d.]+x; whole 2M run [\d.]+x \(goal <= 1.3x: not judged", out
    )


def test_projection_adds_the_growth_of_re_embedding_with_the_buffer() -> None:
    loop = LoopResult("map20", 10_000, 10.0, 100, 5.0, 0.0, 32, 10_000, 20_000, 12.0)
    base = loop.hours(2_000_000, True)
    # 1 us per state, t_emb 10k, capacity 1M: trainings k = 1..200 re-embed min(10k k, 1M) - 10k states.
    hours, extra = project(loop, 1e-6, 0.0, 10_000, 1_000_000, 3_200)
    expected = sum(1e-6 * max(0, min(10_000 * k, 1_000_000) - 10_000) for k in range(1, 201)) / 3600
    assert extra == pytest.approx(expected) and hours == pytest.approx(base + expected)
    _, with_inserts = project(loop, 0.0, 0.032, 10_000, 1_000_000, 3_200)
    assert with_inserts == pytest.approx(0.032 * (2_000_000 - 20_000) / 3_200 / 3600)


def test_emc_run_prints_its_ratio_to_qmix_against_its_own_goal(capsys: pytest.CaptureFixture[str]) -> None:
    args = ["--map", "map10", "--algo", "emc", "--quick", "--loop-steps", "1", "--entries", "500"]
    assert main([*args, "--threads", "1"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"^emc\s+[\d,]+\s+[\d.]+", out, re.M)
    assert re.search(r"ratio emc / qmix: .* \(goal <= 2x: not judged", out)
    assert re.search(r"^EMC vs QMIX: \d+\.\d\dx \(whole run, map10, load average", out, re.M)
