"""``mcrs-bench-benchmarl``: both sides get the same settings, a side that cannot run is recorded with its
cause, and the figures and curve land in the JSON. Everything but the training runs without BenchMARL."""

from __future__ import annotations

import math
import pickle
import sys
from dataclasses import asdict, replace
from pathlib import Path

import pytest
import torch
from bench_helpers import run_json
from mcrs_benchmarks.benchmarl_side import EvaluationRecord, benchmarl_fields, team_return
from mcrs_benchmarks.vs_benchmarl import (
    DEFAULT_PYTHON,
    Settings,
    SideResult,
    curve_rows,
    main,
    ours_overrides,
    run_benchmarl,
)
from tensordict import TensorDict

import mcrs


@pytest.mark.parametrize("settings", [Settings(), Settings(n_envs=8, updates_per_batch=4, frames=8000)])
def test_both_sides_get_the_same_budget_networks_and_schedule(settings: Settings) -> None:
    config = mcrs.compose(*ours_overrides(settings))
    fields = benchmarl_fields(asdict(settings))
    exp, t, algo = fields["experiment"], config.train, config.algo
    T = settings.max_steps
    assert exp["max_n_frames"] == t.total_env_steps == settings.frames
    assert exp["off_policy_collected_frames_per_batch"] == t.num_envs * T
    assert exp["off_policy_n_envs_per_worker"] == t.num_envs
    assert exp["off_policy_n_optimizer_steps"] == t.num_envs * t.updates_per_episode
    assert exp["off_policy_train_batch_size"] == t.batch_episodes * T  # transitions per update
    assert exp["off_policy_memory_size"] == t.replay_episodes * T
    # a target copy every k updates: ours counts episodes, made at updates_per_episode updates each
    assert exp["hard_target_update_frequency"] == t.target_update_episodes * t.updates_per_episode
    assert exp["soft_target_update"] is False
    assert (exp["lr"], exp["adam_eps"], exp["clip_grad_val"]) == (t.lr, t.optim_eps, t.grad_clip)
    assert str(t.optimizer) in ("adam", "Optimizer.adam")
    assert exp["gamma"] == algo.gamma
    eps = (exp["exploration_eps_init"], exp["exploration_eps_end"], exp["exploration_anneal_frames"])
    assert eps == (t.eps_start, t.eps_end, t.eps_anneal_steps)
    assert (exp["evaluation_interval"], exp["evaluation_episodes"]) == (t.eval_interval, t.eval_episodes)
    assert fields["algorithm"]["mixing_embed_dim"] == algo.mixing_embed_dim and algo.hypernet_layers == 1
    assert fields["model"]["num_cells"] == [config.model.hidden_dim] * 2
    assert not config.model.agent_id and not config.model.last_action  # BenchMARL's MLP: observation only
    assert not algo.double_q and algo.td_lambda == 0.0  # TorchRL's QMixerLoss: one-step, target max
    assert algo.reward_scale * settings.scenario_kwargs["n_agents"] == pytest.approx(1.0)  # the agents' mean
    assert fields["task"] == {"max_steps": T, **settings.scenario_kwargs}
    assert config.seed == settings.seed


def test_settings_that_would_break_the_alignment_are_named() -> None:
    assert Settings().problems() == []
    assert "frames=40100" in Settings(frames=40_100).problems()[0]
    assert "eval_interval=1000" in Settings(eval_interval=1000).problems()[0]
    assert (
        "target_update_updates=5"
        in replace(Settings(), target_update_updates=5, updates_per_batch=32).problems()[0]
    )


def test_curve_rows_put_both_sides_evaluations_on_one_frame_axis() -> None:
    ours = SideResult([(0, -1.0), (800, 0.5), (1600, 1.5)], 1600, 100.0, 20.0)
    theirs = SideResult([(800, 0.0), (1600, 2.0)], 1600, 10.0, 2.0)
    rows = curve_rows({"ours": ours, "benchmarl": theirs})
    assert rows == [
        {"frames": 0, "ours": -1.0, "benchmarl": None},
        {"frames": 800, "ours": 0.5, "benchmarl": 0.0},
        {"frames": 1600, "ours": 1.5, "benchmarl": 2.0},
    ]
    assert ours.seconds_per(100_000) == pytest.approx(80.0 * 100_000 / 1600)  # evaluation left out
    assert ours.seconds_per(100_000, with_eval=True) == pytest.approx(100.0 * 100_000 / 1600)
    assert ours.final_return == 1.5 and math.isnan(SideResult(error="x").seconds_per())
    assert ours.tail_return(0.5) == pytest.approx(1.0)  # the evaluations at 800 and 1600 frames
    assert ours.tail_return(0.1) == 1.5 and math.isnan(SideResult().tail_return())


def test_team_return_sums_the_agents_rewards_up_to_the_first_done() -> None:
    reward = torch.tensor([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]]).unsqueeze(-1)  # [T, N, 1]
    done = torch.tensor([False, True, True]).unsqueeze(-1)
    rollout = TensorDict({("next", "agents", "reward"): reward, ("next", "done"): done}, batch_size=[3])
    assert team_return(rollout) == 10.0
    rollout.set(("next", "done"), torch.zeros(3, 1, dtype=torch.bool))
    assert team_return(rollout) == 21.0


def test_the_callback_pickles_without_its_experiment() -> None:
    record = EvaluationRecord()
    record.experiment = lambda: None  # an experiment cannot be pickled; BenchMARL pickles its callbacks
    record.evaluations.append({"frames": 800, "return": 1.0})
    assert pickle.loads(pickle.dumps(record)).evaluations == [{"frames": 800, "return": 1.0}]


def test_a_benchmarl_side_that_cannot_start_is_recorded_with_its_cause(tmp_path: Path) -> None:
    missing = tmp_path / "no_venv" / "python"
    data = run_json(
        main, tmp_path / "r.json", ["--quick", "--sides", "benchmarl", "--benchmarl-python", str(missing)]
    )
    figure = data["figures"]["benchmarl.final_return"]
    assert figure["valid"] is False and figure["value"] is None and str(missing) in figure["note"]
    assert data["figures"]["benchmarl.s_per_100k_frames"]["valid"] is False
    assert data["tables"]["sides"][0]["error"] and data["tables"]["curve"] == []
    assert data["figures"]["benchmarl.tail_return"]["valid"] is False
    assert "time_ratio" not in data["figures"]  # one side only: no ratio
    assert data["arguments"]["benchmarl_fields"]["experiment"]["max_n_frames"] == 80


def test_a_python_without_benchmarl_is_one_line_naming_the_missing_module() -> None:
    result = run_benchmarl(Settings(), sys.executable)  # our environment: no benchmarl
    assert result.error.startswith(f"{sys.executable} exited with 1: ")
    assert "benchmarl" in result.error and not result.evaluations


@pytest.mark.parametrize(
    "argv, words",
    [
        (["--frames", "0"], "--frames must be >= 1"),
        (["--frames", "1000"], "frames=1000 is not a whole number"),
    ],
)
def test_bad_arguments_are_refused_naming_the_argument(
    argv: list[str], words: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit):
        main([*argv, "--json", "none"])
    assert words in capsys.readouterr().err


@pytest.mark.slow
def test_our_side_trains_and_records_its_curve_and_clock(tmp_path: Path) -> None:
    data = run_json(main, tmp_path / "r.json", ["--quick", "--sides", "ours"])
    assert [row["frames"] for row in data["tables"]["curve"]] == [0, 40, 80]
    assert all(row["ours"] is not None for row in data["tables"]["curve"])
    for name in ("ours.s_per_100k_frames", "ours.s_per_100k_frames_with_eval"):
        assert data["figures"][name]["valid"] and data["figures"][name]["value"] > 0
    side = data["tables"]["sides"][0]
    assert side["frames"] == 80 and 0 < side["eval_s"] < side["wall_s"]


@pytest.mark.slow
@pytest.mark.skipif(not Path(DEFAULT_PYTHON).exists(), reason=f"no BenchMARL environment at {DEFAULT_PYTHON}")
def test_both_sides_train_and_the_ratio_is_recorded(tmp_path: Path) -> None:
    data = run_json(main, tmp_path / "r.json", ["--quick"])
    theirs = data["figures"]["benchmarl.final_return"]
    assert theirs["valid"], theirs["note"]
    rows = data["tables"]["curve"]
    assert [r["frames"] for r in rows] == [0, 40, 80] and rows[0]["benchmarl"] is None
    assert all(r["benchmarl"] is not None for r in rows[1:])  # BenchMARL evaluates after its first batch
    assert data["figures"]["time_ratio"]["value"] > 0
