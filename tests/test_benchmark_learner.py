"""The learner benchmark runs end to end at tiny sizes and its fairness check bites (no timing assertions)."""

from __future__ import annotations

import re

import pytest
import torch

from mcrs.benchmarks import learner as bench
from mcrs.benchmarks.learner import main

NUMBER = r"([\d,]+(?:\.\d+)?)"


def test_quick_run_prints_agreement_update_rows_ratio_and_loop(capsys: pytest.CaptureFixture[str]) -> None:
    threads = torch.get_num_threads()
    assert main(["--quick", "--maps", "map10", "--updates", "2", "--threads", "1"]) == 0
    assert torch.get_num_threads() == threads  # restored after the run (the Trainer also sets threads)
    out = capsys.readouterr().out
    assert "command: mcrs-bench-learner --quick --maps map10 --updates 2 --threads 1" in out
    assert "torch threads=1," in out
    assert "losses agree: yes" in out, out
    for learner in ("ours", "reference"):
        row = re.search(rf"^map10\s+{learner}\s+{NUMBER}\s+{NUMBER}\s+{NUMBER}\s*$", out, flags=re.M)
        assert row is not None, out
        assert float(row.group(3)) > 0
    ratio = re.search(
        rf"^ratio map10: ours / reference = {NUMBER}x per update .*goal <= 1.15x", out, flags=re.M
    )
    assert ratio is not None and float(ratio.group(1)) > 0, out
    collect = re.search(rf"^map10  1 env {NUMBER} ms/step, 32 envs {NUMBER} ms/step", out, flags=re.M)
    assert collect is not None and float(collect.group(1)) > 0 and float(collect.group(2)) > 0, out
    loop = re.search(
        rf"^map10\s+{NUMBER}\s+{NUMBER}\s+{NUMBER}\s+{NUMBER}\s+{NUMBER}\s+{NUMBER}", out, flags=re.M
    )
    assert loop is not None, out
    assert float(loop.group(1).replace(",", "")) == 2 * 4 * 6  # two whole 4-env batches of 6 steps
    assert float(loop.group(2).replace(",", "")) > 0
    assert not re.search(r"^map20\s", out, flags=re.M)  # only the requested map
    assert "goals:" not in out  # --quick judges nothing


def test_agreement_check_catches_a_reference_that_computes_another_loss(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    class SingleQReference(bench.ReferenceLearner):
        """Bootstraps with the target network's own argmax: not our (double-Q) loss."""

        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, **kwargs)
            self.double_q = False

    monkeypatch.setattr(bench, "ReferenceLearner", SingleQReference)
    assert main(["--quick", "--maps", "map10", "--updates", "1", "--loop-steps", "0", "--threads", "1"]) == 0
    out = capsys.readouterr().out
    assert "losses agree: no" in out, out
    assert "training loop" not in out  # --loop-steps 0


def test_synthetic_episodes_are_valid() -> None:
    config = bench.from_mapping(bench.compose_config("map10", quick=True).env)
    episodes = bench.synthetic_episodes(5, config, torch.Generator().manual_seed(1))
    T = config.max_steps
    assert episodes.batch_size == (5, T + 1)
    mask, action = episodes["agents", "action_mask"], episodes["agents", "action"]
    assert mask.any(-1).all()  # every agent has an allowed action at every step
    assert mask[:, :-1].gather(-1, action[:, :-1].unsqueeze(-1)).all()  # only allowed actions were taken
    assert episodes["done"][:, T - 1 :].all() and not episodes["done"][:, : T - 1].any()
    assert not episodes["terminated"][:, : T - 1].any()
    assert episodes["filled"][:, :-1].all() and not episodes["filled"][:, -1].any()


def test_bad_arguments_are_rejected() -> None:
    for argv in (["--updates", "0"], ["--loop-steps", "-1"], ["--threads", "-1"], ["--maps", "map99"],
                 ["--launcher-steps", "-1"]):  # fmt: skip
        with pytest.raises(SystemExit):
            main(argv)


def test_launcher_comparison_runs_both_layouts_and_prints_the_ratio(
    capsys: pytest.CaptureFixture[str],
) -> None:
    args = ["--quick", "--maps", "map10", "--updates", "1", "--loop-steps", "0", "--launcher-steps", "1"]
    assert main([*args, "--threads", "1"]) == 0
    out = capsys.readouterr().out
    rates = re.search(
        rf"^one 2-thread run: {NUMBER} env-steps/s; two 1-thread runs: {NUMBER} \+ {NUMBER} = {NUMBER}",
        out,
        re.M,
    )
    assert rates is not None and all(float(g.replace(",", "")) > 0 for g in rates.groups()), out
    ratio = re.search(
        rf"^two 1-thread runs vs one 2-thread run: {NUMBER}x \(aggregate env-steps/s", out, re.M
    )
    assert ratio is not None and float(ratio.group(1)) > 0, out
