"""``mcrs-bench-resources`` at a tiny size: the RSS curve, the bounded stores and the 50% -> 100% verdict,
read from the JSON it writes."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from mcrs_benchmarks.resources import Sample, growth, main

pytestmark = pytest.mark.slow

TINY_RUN = [
    "--env-steps", "800", "--every", "200", "--replay-episodes", "8",
    "--override", "env.max_steps=10", "--override", "train.num_envs=4", "--override", "train.batch_episodes=4",
    "--override", "train.eval_episodes=2", "--override", "train.eval_interval=400",
    "--override", "model.hidden_dim=16", "--override", "train.checkpoint_interval=400",
]  # fmt: skip


def _run(tmp_path: Path, argv: list[str]) -> dict[str, Any]:
    path = tmp_path / "resources.json"
    assert main([*argv, "--json", str(path)]) == 0
    return json.loads(path.read_text())


def test_tiny_run_records_the_curve_and_the_verdict(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    data = _run(tmp_path, TINY_RUN)
    assert data["arguments"]["algo"] == "qmix" and data["arguments"]["env_steps"] == 800
    rows = data["tables"]["samples"]
    assert [r["env_steps"] for r in rows] == [0, 200, 400, 600, 800]
    assert all(r["rss_mib"] > 50 for r in rows)  # a python process with torch: tens of MiB at least
    assert rows[0]["replay_episodes"] == 0 and max(r["replay_episodes"] for r in rows) == 8  # fills, stays
    figures = data["figures"]
    assert figures["replay_full_at_half"]["value"] is True
    assert "memory_entries_at_half" not in figures  # QMIX has no episodic memory
    half, end = rows[2]["rss_mib"], rows[-1]["rss_mib"]  # the first sample at 50% of the run, the last
    assert figures["rss_mib_half"]["value"] == half and figures["rss_mib_end"]["value"] == end
    growth_fig = figures["rss_growth_percent"]
    assert growth_fig["value"] == pytest.approx(100 * (end - half) / half)
    assert growth_fig["goal"] == "< 5" and growth_fig["passed"] is (growth_fig["value"] < 5)
    out = capsys.readouterr().out
    assert out.startswith("MCRS resource benchmark: qmix on map10, 800 env steps, replay 8 episodes, ")
    assert f"= {growth_fig['value']:+.2f}% (goal < 5%): {'PASS' if growth_fig['passed'] else 'FAIL'}" in out


def test_cnn_semu_records_memory_entries(tmp_path: Path) -> None:
    memory = ["--override", "algo.memory.capacity=60", "--override", "algo.memory.embedding_samples=32",
              "--override", "algo.memory.embedding_batch=16", "--override", "algo.memory.hidden_dim=16",
              "--override", "algo.memory.cnn_channels=[2,4,4]", "--override", "algo.memory.embedding_interval=200"]  # fmt: skip
    data = _run(tmp_path, ["--algo", "cnn_semu", *TINY_RUN, *memory])
    rows = data["tables"]["samples"]
    assert rows[-1]["memory_entries"] > 0 and all(r["memory_entries"] <= 60 for r in rows)  # bounded
    assert 0 < data["figures"]["memory_entries_at_half"]["value"] <= 60


def test_growth_is_measured_from_the_middle_of_the_run() -> None:
    samples = [Sample(0, 100.0, 0, 0), Sample(50, 200.0, 8, 0), Sample(100, 220.0, 8, 0)]
    middle, last, rise = growth(samples, 100)
    assert (middle.env_steps, last.env_steps) == (50, 100)
    assert rise == pytest.approx(0.10)  # 10%: a FAIL against < 5%
