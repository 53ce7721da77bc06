"""The learner benchmark runs end to end at tiny sizes, records its figures as JSON and its fairness check
bites (no timing assertions)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import torch
from mcrs_benchmarks import learner as bench
from mcrs_benchmarks.common import compose_config, synthetic_episodes
from mcrs_benchmarks.learner import main
from mcrs_benchmarks.reference_learner import ReferenceLearner

from mcrs.env.config import from_mapping
from tests.bench_helpers import run_json

pytestmark = pytest.mark.slow


def _run(tmp_path: Path, argv: list[str]) -> dict[str, Any]:
    return run_json(main, tmp_path / "learner.json", argv)


def test_quick_run_records_agreement_update_rows_ratio_and_loop(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    threads = torch.get_num_threads()
    data = _run(tmp_path, ["--quick", "--maps", "map10", "--updates", "2", "--threads", "1"])
    assert torch.get_num_threads() == threads  # restored after the run (the Experiment also sets threads)
    assert data["command"].startswith("mcrs-bench-learner --quick --maps map10 --updates 2 --threads 1")
    assert data["machine"]["torch_threads"] == 1
    figures, tables = data["figures"], data["tables"]
    assert figures["map10.loss_rel_diff"]["passed"] is True  # the two learners compute the same loss
    updates = {row["learner"]: row for row in tables["updates"]}
    assert set(updates) == {"ours", "reference"} and {row["map"] for row in tables["updates"]} == {"map10"}
    for label, row in updates.items():
        assert row["sample_ms"] > 0 and row["update_ms"] > 0
        assert figures[f"map10.update_ms.{label}"]["value"] == pytest.approx(
            row["sample_ms"] + row["update_ms"]
        )
    ratio = figures["map10.update_ratio"]
    assert ratio["value"] > 0 and ratio["goal"] == "<= 1.15" and ratio["unit"] == "x"
    assert ratio["not_judged"] == "--quick" and ratio["passed"] is None and ratio["valid"] is True
    (collector,) = tables["collector"]
    assert (
        collector["map"] == "map10"
        and collector["ms_per_step_1_env"] > 0
        and collector["ms_per_step_32_envs"] > 0
    )
    (loop,) = tables["loop"]
    assert loop["window_steps"] == 2 * 4 * 6  # two whole 4-env batches of 6 steps
    assert (
        loop["env_steps_per_s"] > 0
        and figures["map10.loop_env_steps_per_s"]["value"] == loop["env_steps_per_s"]
    )
    assert (
        figures["map10.hours"]["value"] == pytest.approx(loop["hours"])
        and figures["map10.hours"]["goal"] is None
    )
    assert not any(name.startswith("map20") for name in figures)  # only the requested map
    assert data["passed"] is True  # only the agreement is judged under --quick
    out = capsys.readouterr().out
    assert "losses agree: yes" in out
    assert f"ratio map10: ours / reference = {ratio['value']:.2f}x per update" in out
    assert "goals:" not in out  # --quick judges nothing


def test_agreement_check_catches_a_reference_that_computes_another_loss(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    class SingleQReference(ReferenceLearner):
        """Bootstraps with the target network's own argmax: not our (double-Q) loss."""

        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, **kwargs)
            self.double_q = False

    monkeypatch.setattr(bench, "ReferenceLearner", SingleQReference)
    argv = ["--quick", "--maps", "map10", "--updates", "1", "--loop-steps", "0", "--threads", "1"]
    data = _run(tmp_path, argv)
    figures = data["figures"]
    assert (
        figures["map10.loss_rel_diff"]["value"] > 1e-5 and figures["map10.loss_rel_diff"]["passed"] is False
    )
    assert figures["map10.update_ratio"]["valid"] is False  # the timing comparison is void
    assert data["passed"] is False
    assert "loop" not in data["tables"]  # --loop-steps 0
    assert "losses agree: no" in capsys.readouterr().out


def test_the_reference_learner_refuses_what_it_does_not_implement() -> None:
    cfg = compose_config("map10", quick=True, algo="vdn")
    with pytest.raises(ValueError, match="the reference learner is QMIX with 2-layer hypernets"):
        ReferenceLearner(cfg, from_mapping(cfg.env))


def test_synthetic_episodes_are_valid() -> None:
    config = from_mapping(compose_config("map10", quick=True).env)
    episodes = synthetic_episodes(5, config, torch.Generator().manual_seed(1))
    T = config.max_steps
    assert episodes.batch_size == (5, T + 1)
    mask, action = episodes["agents", "action_mask"], episodes["agents", "action"]
    assert mask.any(-1).all()  # every agent has an allowed action at every step
    assert mask[:, :-1].gather(-1, action[:, :-1].unsqueeze(-1)).all()  # only allowed actions were taken
    assert episodes["done"][:, T - 1 :].all() and not episodes["done"][:, : T - 1].any()
    assert not episodes["terminated"][:, : T - 1].any()
    assert episodes["filled"][:, :-1].all() and not episodes["filled"][:, -1].any()


@pytest.mark.parametrize(
    ("argv", "message"),
    [(["--updates", "0"], "--updates must be >= 1, got 0"), (["--loop-steps", "-1"], "--loop-steps must be >= 0"),
     (["--threads", "-1"], "--threads must be >= 0"), (["--maps", "map99"], "invalid choice: 'map99'"),
     (["--launcher-steps", "-1"], "--launcher-steps must be >= 0, got -1")],
)  # fmt: skip
def test_bad_arguments_are_rejected_naming_the_argument(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit):
        main(argv)
    assert message in capsys.readouterr().err


def test_launcher_comparison_runs_both_layouts_and_records_the_ratio(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["--quick", "--maps", "map10", "--updates", "1", "--loop-steps", "0", "--launcher-steps", "1"]
    figures = _run(tmp_path, [*argv, "--threads", "1"])["figures"]
    one = figures["launcher.one_2_thread_env_steps_per_s"]["value"]
    two = figures["launcher.two_1_thread_env_steps_per_s"]["value"]
    ratio = figures["launcher.ratio"]
    assert one > 0 and two > 0 and ratio["value"] == pytest.approx(two / one) and ratio["unit"] == "x"
    assert f"two 1-thread runs vs one 2-thread run: {ratio['value']:.2f}x (aggregate env-steps/s" in (
        capsys.readouterr().out
    )
