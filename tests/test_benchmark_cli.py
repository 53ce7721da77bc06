"""The throughput benchmark runs end to end and prints a parsable table (no timing assertions)."""

from __future__ import annotations

import re

import pytest
import torch
from tensordict import TensorDict

from mcrs.benchmarks import env_throughput
from mcrs.benchmarks.env_throughput import main
from mcrs.env import scenario
from mcrs.policies import RandomPolicy

NUMBER = r"([\d,]+(?:\.\d+)?)"


def _value(text: str) -> float:
    return float(text.replace(",", ""))


def test_main_prints_a_row_per_map_and_batch_size_and_the_ratio(capsys: pytest.CaptureFixture[str]) -> None:
    threads = torch.get_num_threads()
    argv = ["--maps", "map10", "--num-envs", "1", "4", "--seconds", "0.2", "--skip-memory", "--threads", "1"]
    assert main(argv) == 0
    assert torch.get_num_threads() == threads  # restored after the run
    out = capsys.readouterr().out
    assert "torch threads=1," in out
    for path, num_envs in [("MCRSEnv", 1), ("MCRSEnv", 4), ("PettingZoo", 1)]:
        rows = re.findall(rf"^map10\s+{path}\s+{num_envs}\s+{NUMBER}\s+{NUMBER}\s*$", out, flags=re.M)
        assert len(rows) == 1, out
        env_steps, agent_steps = map(_value, rows[0])
        assert env_steps > 0
        assert agent_steps == pytest.approx(4 * env_steps, rel=1e-3, abs=2)  # map10 has 4 UAVs
    assert not re.search(r"^map(15|20)\s", out, flags=re.M)  # only the requested map
    ratio = re.search(rf"^ratio map10: MCRSEnv@4 / PettingZoo loop = {NUMBER}x", out, flags=re.M)
    assert ratio is not None and _value(ratio.group(1)) > 0, out
    assert "memory" not in out  # --skip-memory
    assert "goals:" in out and "n/a (not measured)" in out  # map20 @1024 was not run


def test_memory_section_reports_bytes_per_env_and_projection(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(env_throughput, "MEMORY_NUM_ENVS", 16)  # keep the measured check tiny
    assert main(["--maps", "map10", "--num-envs", "2", "--seconds", "0.1"]) == 0
    out = capsys.readouterr().out
    per_env = dict(re.findall(rf"^\s+(map\d\d)\s+{NUMBER} bytes/env$", out, flags=re.M))
    assert set(per_env) == {"map10", "map15", "map20"}
    assert 0 < _value(per_env["map10"]) < _value(per_env["map15"]) < _value(per_env["map20"])
    projection = re.search(rf"projection, 16 map20 envs: {NUMBER} GiB", out)
    assert projection is not None
    assert _value(projection.group(1)) == pytest.approx(16 * _value(per_env["map20"]) / 2**30, abs=1e-3)
    assert re.search(r"VmRSS [+-][\d.]+ GiB", out), out
    assert re.search(r"16 map20 envs <= 2 GiB: projected [\d.]+ GiB PASS", out), out


def test_the_benchmark_policy_draws_only_allowed_actions() -> None:
    policy = RandomPolicy(scenario("map10", n_uavs=3), seed=0)
    mask = torch.zeros(256, 3, 8, dtype=torch.bool)
    mask[..., 2] = mask[..., 5] = True
    mask[0, 0] = True
    td = TensorDict({"agents": TensorDict({"action_mask": mask}, batch_size=[256, 3])}, batch_size=[256])
    actions = policy(td)["agents", "action"]
    assert actions.shape == (256, 3)
    assert mask.gather(-1, actions.unsqueeze(-1)).all()
    assert set(actions[1:].unique().tolist()) == {2, 5}  # both allowed moves are drawn


def test_bad_arguments_are_rejected() -> None:
    with pytest.raises(SystemExit):
        main(["--num-envs", "0"])
    with pytest.raises(SystemExit):
        main(["--maps", "map99"])
    with pytest.raises(SystemExit):
        main(["--threads", "-1"])
