"""Checkpoints written before the callbacks and the typed env node still load: their layout is mapped."""

from __future__ import annotations

import torch

from mcrs.experiment import checkpoint as ckpt


def test_a_checkpoint_from_before_the_callbacks_is_mapped_to_todays_layout() -> None:
    memory = {"memory": {"keys": torch.zeros(3, 4)}, "embedding": {"w": torch.ones(2)}}
    curiosity = {"modules": {"w": torch.ones(1)}}
    legacy = {
        "learner": {"agent": {"w": torch.ones(3)}, "curiosity": curiosity},
        "episodic": memory,
        "counters": {"env_steps": 400, "next_embedding": 480},
        "last_eval": {"episode_reward": 7.5},
    }
    state = ckpt.current_layout(legacy)
    assert "curiosity" not in state["learner"] and state["learner"]["agent"] is legacy["learner"]["agent"]
    assert state["callbacks"]["curiosity"] is curiosity
    assert state["callbacks"]["memory"]["memory"] is memory["memory"]
    assert state["callbacks"]["memory"]["next_embedding"] == 480  # the schedule moved into the callback
    assert state["callbacks"]["memory"]["last_eval_reward"] == 7.5  # EMU-change's threshold
    assert ckpt.current_layout(state) is state  # today's layout passes through


def test_a_saved_config_loses_the_env_runtime_fields_only() -> None:
    saved = {"env": {"name": "map10", "width": 10, "num_envs": 32, "device": "cpu"}, "seed": 3}
    # ... and gains the fields it predates, at the value it was made under (safety_rule: near).
    assert ckpt.current_config(saved) == {
        "env": {"name": "map10", "width": 10, "safety_rule": "near"},
        "seed": 3,
    }
    assert ckpt.current_config({"seed": 3}) == {"seed": 3}
