"""The env config group: presets are paper tables 2-3, and every field is overridable from Hydra."""

import math

import pytest
from hydra import compose, initialize_config_dir

from mcrs.env.config import RUNTIME_FIELDS, SCENARIOS, field_names, from_mapping, scenario
from mcrs.evaluate import CONFIG_DIR

# Paper table 2: grid, UAVs, targets, no-fly zones, T; table 3: R_c = 5, R_sight = 4, d1 = d2 = 1,
# m_f = m_e = 0.8, w1..w4 = 1; tau = 0.95 (the spec).
TABLE_2 = {"map10": (10, 4, 6, 3, 50), "map15": (15, 8, 12, 6, 70), "map20": (20, 10, 20, 10, 100)}

# A valid, non-default value for every field of the environment config.
OVERRIDES = {
    "name": ("custom", "custom"),
    "width": ("12", 12),
    "height": ("9", 9),
    "n_uavs": ("5", 5),
    "n_targets": ("7", 7),
    "n_no_fly": ("2", 2),
    "max_steps": ("33", 33),
    "no_fly_view": ("belief", "belief"),
    "no_fly_prior": ("unknown", "unknown"),
    "discovery_rule": ("target", "target"),
    "relative_order": ("nearest", "nearest"),
    "comm_range": ("inf", math.inf),
    "comm_rounds": ("flood", "flood"),
    "sight_range": ("3.5", 3.5),
    "no_fly_safety": ("1.5", 1.5),
    "uav_safety": ("2", 2.0),
    "safety_rule": ("near", "near"),
    "m_f": ("0.7", 0.7),
    "m_e": ("0.6", 0.6),
    "p_detect": ("0.9", 0.9),
    "p_false_alarm": ("0.1", 0.1),
    "w_uncertainty": ("2", 2.0),
    "w_discovery": ("3", 3.0),
    "w_no_fly": ("0.5", 0.5),
    "w_collision": ("0", 0.0),
    "target_threshold": ("0.9", 0.9),
    "invalid_action": ("clip", "clip"),
    "expose_beliefs": ("true", True),
    "no_fly_shield": ("true", True),
    "uav_shield": ("true", True),
    "far_view": ("2", 2),
    "comm_delay": ("2", 2),
    "comm_budget": ("6", 6),
    "target_motion": ("random_walk", "random_walk"),
    "target_move_prob": ("0", 0.0),  # > 0 needs target_motion=random_walk (one override at a time here)
    "evidence_decay": ("0.01", 0.01),
}


def compose_env(name: str, overrides: list[str]):
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base=None):
        return from_mapping(compose("eval", overrides=[f"env={name}", *overrides]).env)


@pytest.mark.parametrize("name", SCENARIOS)
def test_presets_are_the_paper_tables(name):
    cfg = scenario(name)
    size, n_uavs, n_targets, n_no_fly, steps = TABLE_2[name]
    assert (cfg.width, cfg.height, cfg.n_uavs, cfg.n_targets, cfg.n_no_fly, cfg.max_steps) == (
        size, size, n_uavs, n_targets, n_no_fly, steps,
    )  # fmt: skip
    assert (cfg.comm_range, cfg.sight_range, cfg.no_fly_safety, cfg.uav_safety) == (5.0, 4.0, 1.0, 1.0)
    assert (cfg.m_f, cfg.m_e, cfg.target_threshold) == (0.8, 0.8, 0.95)
    assert (cfg.w_uncertainty, cfg.w_discovery, cfg.w_no_fly, cfg.w_collision) == (1.0, 1.0, 1.0, 1.0)
    assert compose_env(name, []) == cfg  # Hydra and Python see the same preset


def test_every_field_has_an_override_here():
    """Every scenario field; the runtime fields (num_envs, device) come from train.num_envs and device."""
    assert set(OVERRIDES) == set(field_names()) - set(RUNTIME_FIELDS)


@pytest.mark.parametrize("field", sorted(OVERRIDES))
def test_every_field_is_overridable_from_the_command_line(field):
    text, expected = OVERRIDES[field]
    cfg = compose_env("map20", [f"env.{field}={text}"])
    assert getattr(cfg, field) == expected
    default = scenario("map20")
    assert all(getattr(cfg, other) == getattr(default, other) for other in field_names() if other != field)


@pytest.mark.parametrize("field", RUNTIME_FIELDS)
def test_runtime_fields_are_not_scenario_keys(field):
    with pytest.raises(Exception, match=field):
        compose_env("map10", [f"env.{field}=1"])


def test_bad_override_fails_with_the_field_named():
    with pytest.raises(ValueError, match=r"p_false_alarm=1.5: must be a probability in \[0, 1\]"):
        compose_env("map10", ["env.p_false_alarm=1.5"])
