"""The memory estimate behind the refusal of sizes the machine cannot hold (mcrs/experiment/training/resources.py)
measured against the stores a run really allocates."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from mcrs.env.config import from_mapping
from mcrs.experiment.training.episodic import EpisodicMemoryCallback
from mcrs.experiment.training.resources import estimate, memory_entry_bytes, replay_step_bytes
from mcrs.experiment.training.trainer import Experiment
from tests.train_helpers import compose_config


@pytest.mark.slow
def test_the_replay_estimate_is_the_bytes_a_full_buffer_holds(tmp_path: Path) -> None:
    cfg = compose_config("train.total_env_steps=200")  # 20 episodes: the tiny buffer is full
    trainer = Experiment(cfg, tmp_path / "run")
    trainer.run()
    assert len(trainer.replay) == cfg.train.replay_episodes
    held = sum(v.numel() * v.element_size() for v in trainer.replay.storage._storage.values(True, True))
    T = trainer.env_config.max_steps
    assert replay_step_bytes(trainer.env_config) * (T + 1) * cfg.train.replay_episodes == held
    stores = {s.name: s.nbytes for s in estimate(cfg, trainer.env_config)}
    assert stores["replay buffer"] == held


def test_the_episodic_memory_estimate_covers_what_it_allocates() -> None:
    """Per entry, within +30 % of the memory's own ``nbytes`` (never below it), on the smallest and
    largest map."""
    for env in ("map10", "map20"):
        sizes = []
        for capacity in (1000, 2000):
            cfg = compose_config(
                "algo=cnn_semu", f"env={env}", f"algo.memory.capacity={capacity}", tiny=False
            )
            sizes.append(
                EpisodicMemoryCallback(cfg, from_mapping(cfg.env), torch.device("cpu")).memory.nbytes()
            )
        per_entry = (sizes[1] - sizes[0]) / 1000
        assert (
            per_entry <= memory_entry_bytes(from_mapping(cfg.env), cfg.algo.memory.key_dim) <= 1.3 * per_entry
        )
