"""``mcrs-bench-resources`` at a tiny size: the RSS curve, the bounded stores and the 50% -> 100% verdict."""

from __future__ import annotations

import re

import pytest

from mcrs.benchmarks.resources import Sample, growth, main

TINY_RUN = [
    "--env-steps", "800", "--every", "200", "--replay-episodes", "8",
    "--override", "env.max_steps=10", "--override", "train.num_envs=4", "--override", "train.batch_episodes=4",
    "--override", "train.eval_episodes=2", "--override", "train.eval_interval=400",
    "--override", "model.hidden_dim=16", "--override", "train.checkpoint_interval=400",
]  # fmt: skip


def _rows(out: str) -> list[tuple[int, float, int, int]]:
    """The table rows: env_steps, rss_mib, replay_episodes, memory_entries."""
    pattern = re.compile(r"^\s*(\d+)\s+([\d.]+)\s+(\d+)\s+(\d+)\s*$")
    matches = [pattern.match(line) for line in out.splitlines()]
    return [(int(m[1]), float(m[2]), int(m[3]), int(m[4])) for m in matches if m]


def test_tiny_run_prints_the_curve_and_the_verdict(capsys: pytest.CaptureFixture) -> None:
    assert main(TINY_RUN) == 0
    out = capsys.readouterr().out
    assert "MCRS resource benchmark: qmix on map10, 800 env steps, replay 8 episodes" in out
    assert re.search(r"env_steps\s+rss_mib\s+replay_episodes\s+memory_entries", out)
    rows = _rows(out)
    assert [r[0] for r in rows] == [0, 200, 400, 600, 800]
    assert all(r[1] > 50 for r in rows)  # a python process with torch: tens of MiB at least
    assert rows[0][2] == 0 and max(r[2] for r in rows) == 8  # the replay fills and stays at its capacity
    assert "replay at 50%: full" in out
    assert re.search(r"RSS growth 50% -> 100% \(400 -> 800 env steps\): .* MiB = [+-]\d+\.\d\d% \(goal < 5%\): "
                     r"(PASS|FAIL)", out)  # fmt: skip


def test_cnn_semu_reports_memory_entries(capsys: pytest.CaptureFixture) -> None:
    memory = ["--override", "algo.memory.capacity=60", "--override", "algo.memory.embedding_samples=32",
              "--override", "algo.memory.embedding_batch=16", "--override", "algo.memory.hidden_dim=16",
              "--override", "algo.memory.cnn_channels=[2,4,4]", "--override", "algo.memory.embedding_interval=200"]  # fmt: skip
    assert main(["--algo", "cnn_semu", *TINY_RUN, *memory]) == 0
    out = capsys.readouterr().out
    rows = _rows(out)
    assert rows[-1][3] > 0 and all(r[3] <= 60 for r in rows)  # the memory is bounded by its capacity
    assert "memory at 50%:" in out


def test_growth_is_measured_from_the_middle_of_the_run() -> None:
    samples = [Sample(0, 100.0, 0, 0), Sample(50, 200.0, 8, 0), Sample(100, 220.0, 8, 0)]
    middle, last, rise = growth(samples, 100)
    assert (middle.env_steps, last.env_steps) == (50, 100)
    assert rise == pytest.approx(0.10)  # 10%: a FAIL against < 5%
