"""The penalty rule and the horizon as saved: configs made before ``env.safety_rule`` and
``algo.time_limit`` existed are read as they were made (and said so); the horizon-gap and reward-bound
tools compute what their docs say."""

from __future__ import annotations

import pytest
import torch
import yaml
from omegaconf import OmegaConf
from tensordict import TensorDictBase
from torchrl.collectors import Collector
from torchrl.envs import TransformedEnv
from train_helpers import compose_config

from mcrs.env import MCRSEnv
from mcrs.env.config import EnvConfig, scenario, with_legacy_values
from mcrs.env.core import N_ACTIONS
from mcrs.experiment.config import as_typed, compose, validate
from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.run import history
from mcrs.experiment.training.learner import Learner
from mcrs.experiment.training.replay import episodes_from_rollout
from mcrs.models.acting import make_acting_policy, recurrent_primer
from mcrs.train import resume_config
from mcrs_lab.analysis.bound import reading_gains, reward_bound
from mcrs_lab.analysis.horizon import cut_returns, horizon_gaps
from mcrs_lab.analysis.runs import TrainingRun


def tiny_rollout(env_config: EnvConfig, learner: Learner, episodes: int = 3) -> TensorDictBase:
    """A collector batch ``[episodes, T]`` of whole episodes, acting with ``learner``'s agent."""
    env = TransformedEnv(
        MCRSEnv(env_config.replace(num_envs=episodes)),
        recurrent_primer(episodes, env_config.n_uavs, learner.agent.hidden_dim),
    )
    _, exploring, _ = make_acting_policy(learner.agent, N_ACTIONS)
    collector = Collector(
        env, exploring, frames_per_batch=episodes * env_config.max_steps, total_frames=-1,
        trust_policy=True, auto_register_policy_transforms=False,
    )  # fmt: skip
    batch = next(iter(collector))
    collector.shutdown()
    return batch


def saved_before_the_fields() -> dict:
    """A run's config.yaml as written before 2026-11-26: no env.safety_rule, no algo.time_limit."""
    config = OmegaConf.to_container(compose_config(), resolve=True, enum_to_str=True)
    del config["env"]["safety_rule"], config["algo"]["time_limit"]
    return config


def test_defaults_are_the_papers_reward_and_one_horizon():
    cfg = compose("env=map20")
    assert cfg.env.safety_rule == "enter" and str(cfg.algo.time_limit) == "terminal"


def test_an_old_config_reads_as_near_and_bootstrap_and_says_so():
    old = saved_before_the_fields()
    assert history.legacy_values(old) == ["env.safety_rule=near", "algo.time_limit=bootstrap"]
    current = history.current_config(old)
    assert current["env"]["safety_rule"] == "near" and current["algo"]["time_limit"] == "bootstrap"
    assert "safety_rule" not in old["env"]  # the saved dict itself is not rewritten
    # A config that has the fields keeps them, whatever they are.
    new = {
        **old,
        "env": {**old["env"], "safety_rule": "enter"},
        "algo": {**old["algo"], "time_limit": "terminal"},
    }
    assert history.legacy_values(new) == [] and history.current_config(new)["env"]["safety_rule"] == "enter"
    paper = {
        "safety_rule": "enter",
        "no_fly_view": "blocked",
        "no_fly_prior": "known",
        "discovery_rule": "belief",
    }
    assert with_legacy_values(paper) == (paper, [])


def test_a_config_saved_before_the_no_fly_and_discovery_fields_reads_as_the_lured_task():
    """A run of the first campaign on the paper's reward (safety_rule saved, the zones shown as unread beliefs,
    r2 for real targets) loads as it was made and says so; nothing saved is rewritten."""
    config = OmegaConf.to_container(compose_config(), resolve=True, enum_to_str=True)
    for name in ("no_fly_view", "no_fly_prior", "discovery_rule"):
        del config["env"][name]
    assert history.legacy_values(config) == [
        "env.no_fly_view=belief", "env.no_fly_prior=unknown", "env.discovery_rule=target"
    ]  # fmt: skip
    current = history.current_config(config)["env"]
    assert (
        current["safety_rule"],
        current["no_fly_view"],
        current["no_fly_prior"],
        current["discovery_rule"],
    ) == ("enter", "belief", "unknown", "target")
    assert "no_fly_view" not in config["env"]
    run = TrainingRun(path=None, config=config)  # type: ignore[arg-type]
    assert run.setting("env.discovery_rule") == "target" and run.setting("env.no_fly_prior") == "unknown"


def test_a_record_made_before_the_field_is_read_as_near():
    run = TrainingRun(path=None, config=saved_before_the_fields())  # type: ignore[arg-type]
    assert run.setting("env.safety_rule") == "near" and run.setting("algo.time_limit") == "bootstrap"
    assert run.legacy == ["env.safety_rule=near", "algo.time_limit=bootstrap"]


def test_resuming_an_old_run_keeps_its_rules_and_says_so(tmp_path, capsys):
    run_dir = tmp_path / "old"
    (run_dir / "checkpoints").mkdir(parents=True)
    (run_dir / "checkpoints" / ckpt.LAST).write_bytes(b"")  # resume_config checks it exists; it loads later
    (run_dir / "config.yaml").write_text(yaml.safe_dump(saved_before_the_fields()))
    cfg, _ = resume_config(compose_config(f"resume={run_dir}"), [f"resume={run_dir}"])
    assert cfg.env.safety_rule == "near" and str(cfg.algo.time_limit) == "bootstrap"
    said = capsys.readouterr().out
    assert "written before env.safety_rule, algo.time_limit existed" in said
    assert "env.safety_rule=near, algo.time_limit=bootstrap" in said


def test_cut_returns_are_discounted_sums_that_stop_at_t():
    reward = torch.tensor([[1.0, 2.0, 4.0]])
    returns = cut_returns(reward, 0.5)
    assert returns.tolist() == [[1.0 + 0.5 * 2.0 + 0.25 * 4.0, 2.0 + 0.5 * 4.0, 4.0, 0.0]]


@pytest.mark.parametrize("time_limit", ["terminal", "bootstrap"])
def test_horizon_gap_is_zero_at_the_last_step_only_under_terminal(time_limit):
    cfg = as_typed(compose_config(f"algo.time_limit={time_limit}"))
    env_config = validate(cfg)
    torch.manual_seed(0)
    learner = Learner(cfg.algo, cfg.model, cfg.train, env_config, torch.device("cpu"))
    with torch.no_grad():  # a non-zero value at s_T, so that bootstrapping there shows
        for p in learner.loss.target_mixer_params.values(True, True):
            p.add_(0.5)
    episodes = episodes_from_rollout(tiny_rollout(env_config, learner), time_limit=time_limit)
    gaps = horizon_gaps(learner, episodes, cfg.algo.gamma, terminal=time_limit == "terminal")
    last = gaps["target_gap"][-1].item()
    next_value = learner.loss.bootstrap_values(episodes)[:, -1, 0].mean().item()
    if time_limit == "terminal":
        assert last == 0.0
    else:
        assert last == pytest.approx(cfg.algo.gamma * next_value, rel=1e-5) and last != 0.0
    assert torch.allclose(gaps["target_gap"][:-1], cfg.algo.gamma * gaps["value_gap"][:-1])
    # Under algo.reward_scale the learner's values are in its units: the gaps are read in the env's.
    returns = cut_returns(episodes.get("reward")[:, :-1, 0], cfg.algo.gamma)[:, 1:].mean(0)
    learner.loss.reward_scale = 4.0
    scaled = horizon_gaps(learner, episodes, cfg.algo.gamma, terminal=time_limit == "terminal")
    assert torch.allclose(scaled["value_gap"] + returns, (gaps["value_gap"] + returns) / 4.0, atol=1e-4)


def test_reading_gains_follow_the_belief_rule():
    empty, target = reading_gains(scenario("map20"))
    assert empty[:3].tolist() == pytest.approx([0.8, 0.16, 0.032], rel=1e-5)
    # A target's second reading takes m(F) from 0.8 to 0.96 >= tau = 0.95: discovered, w2 = 1 more.
    assert target[:3].tolist() == pytest.approx([0.8, 1.16, 0.032], rel=1e-5)


def test_the_bound_takes_the_best_readings_and_is_lower_under_near():
    enter = reward_bound(scenario("map10", discovery_rule="target"), episodes=8, seed=0)
    near = reward_bound(scenario("map10", discovery_rule="target", safety_rule="near"), episodes=8, seed=0)
    assert (near < enter).all()
    # map10's 200 readings: the first of each of the 97 free cells, the second of the 6 targets, the
    # second of the 91 other cells, then 6 third readings; no zone cell is worth its -1 under enter.
    assert enter[0].item() == pytest.approx(0.8 * 97 + 6 * 1.16 + 91 * 0.16 + 6 * 0.032, rel=1e-5)


def test_under_eq_24_any_cell_read_f_twice_is_a_discovery_in_the_bound():
    """An empty cell the sensor may read as F (p_false_alarm > 0) can pay w2: its best run is all F."""
    paid = reward_bound(scenario("map10"), episodes=8, seed=0)
    # 97 free cells (3 known zones gain nothing): each first reading 0.8, each second 1.16, then 6 third.
    assert paid[0].item() == pytest.approx(97 * (0.8 + 1.16) + 6 * 0.032, rel=1e-5)
    perfect = reward_bound(scenario("map10", p_detect=1.0, p_false_alarm=0.0), episodes=8, seed=0)
    target_rule = reward_bound(scenario("map10", discovery_rule="target"), episodes=8, seed=0)
    assert torch.allclose(perfect, target_rule)  # a perfect sensor makes no false discovery to pay


def test_a_run_of_one_kind_is_each_cells_best_under_the_default_belief_masses():
    """The bound's premise: over k readings, 1 - m(U) is largest for k readings of one kind."""
    from mcrs.env.belief import belief_masses

    cfg = scenario("map20")
    for k in range(1, 8):
        positive = torch.arange(k + 1)
        _, _, unknown = belief_masses(positive, k - positive, cfg.m_f, cfg.m_e)
        assert unknown.argmin().item() in (0, k)


def test_the_bound_command_reads_fields_and_refuses_bad_ones(capsys):
    from mcrs_lab.analysis.bound import main

    assert main(["--env", "map10", "--episodes", "2", "--set", "p_false_alarm=0.1"]) == 0
    out = capsys.readouterr().out
    assert "p_false_alarm=0.1" in out and "discovery_rule=belief" in out
    with pytest.raises(SystemExit, match="p_detect=2"):
        main(["--env", "map10", "--set", "p_detect=2"])
    with pytest.raises(SystemExit, match="must be FIELD=VALUE"):
        main(["--env", "map10", "--set", "p_detect"])
