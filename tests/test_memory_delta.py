"""What delta means (eq. 35 as a volume per entry, or literally), and that the default reading merges
states of real rollouts and finds other trajectories' memories, while the literal one never does."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from mcrs.env.config import scenario
from mcrs.experiment.training.episodic import EpisodicMemoryCallback
from mcrs.memory.delta import match_tolerance, unit_ball_volume
from tests.test_episodic_memory import rollout
from tests.train_helpers import compose_config


@pytest.mark.parametrize("key_dim", [1, 2, 3, 4, 8])
@pytest.mark.parametrize("delta", [1.3e-4, 1.3e-3, 1.3e-1, 2.0])
def test_volume_reading_gives_each_entry_a_neighbourhood_of_volume_delta(key_dim: int, delta: float) -> None:
    box = match_tolerance(delta, "volume", "box", key_dim)
    ball = match_tolerance(delta, "volume", "ball", key_dim)
    assert (2 * box) ** key_dim == pytest.approx(delta, rel=1e-12)
    assert unit_ball_volume(key_dim) * ball**key_dim == pytest.approx(delta, rel=1e-12)
    assert match_tolerance(delta, "literal", "box", key_dim) == delta
    assert match_tolerance(delta, "literal", "ball", key_dim) == delta


def test_the_papers_delta_read_as_a_volume() -> None:
    # eq. 35 with sigma 1, dim(x) = 4, M = 1M: (2 * 3)^4 / 1e6 = 1.296e-3, table 3's 1.3e-3; its box has
    # a half-side of 3 / M^(1/4) = 0.0949 standardised units, 73x the literal 1.3e-3.
    assert pytest.approx(1.3e-3, rel=0.01) == 6**4 / 1e6
    assert match_tolerance(1.3e-3, "volume", "box", 4) == pytest.approx(0.0950, abs=1e-4)
    assert unit_ball_volume(2) == pytest.approx(math.pi) and unit_ball_volume(3) == pytest.approx(
        4 * math.pi / 3
    )


def test_bad_delta_readings_are_refused() -> None:
    with pytest.raises(ValueError, match=r"delta rule must be one of volume, literal, got 'area'"):
        match_tolerance(1e-3, "area", "box", 4)
    with pytest.raises(ValueError, match=r"shape must be one of ball, box, got 'cube'"):
        match_tolerance(1e-3, "volume", "cube", 4)
    with pytest.raises(ValueError, match=r"delta must be a finite number > 0"):
        match_tolerance(0.0, "volume", "box", 4)


def _insert_two_batches(
    *overrides: str, seeds: tuple[int, int] = (0, 1)
) -> tuple[EpisodicMemoryCallback, list[dict[str, float]], float]:
    """The default CNN-SEMU memory of map10 (untrained CNN) fed two batches of 16 real episodes (ids 0-15,
    then 16-31); returns the side, the insertion diagnostics and the foreign-hit rate of replaying the
    second batch."""
    cfg = compose_config("algo=cnn_semu", *overrides, tiny=False)
    side = EpisodicMemoryCallback(cfg, scenario("map10"), torch.device("cpu"))
    stats = []
    for b, seed in enumerate(seeds):
        # Real states s_0 .. s_{T-1}, as a collector batch of T-1 transitions (root s_t, "next" s_{t+1}).
        state, counts, reward = rollout("map10", num_envs=16, seed=seed)
        T = state.shape[1]
        batch = TensorDict(
            {
                "state": state[:, :-1],
                "state_counts": counts[:, :-1],
                "next": {
                    "reward": reward[:, :-1, None],
                    "state": state[:, 1:],
                    "state_counts": counts[:, 1:],
                },
            },
            batch_size=[16, T - 1],
        )
        stats.append(side.insert(batch, torch.arange(16) + 16 * b, None))
    episodes = TensorDict(
        {"state": state, "episode": (torch.arange(16) + 16).unsqueeze(1).expand(16, T)},
        batch_size=[16, T],
    )
    side.lookup(episodes)
    return side, stats, side.statistics().get("memory/foreign_hit_rate", 0.0)


def test_the_default_reading_merges_states_of_real_rollouts() -> None:
    side, stats, _ = _insert_two_batches()
    assert side.memory.shape == "box" and side.tolerance == pytest.approx(0.0950, abs=1e-4)
    assert all(s["memory/insert_hit_rate"] > 0.02 for s in stats)


def test_foreign_hits_count_entries_written_by_other_episodes() -> None:
    """The second batch repeats the first's episodes under new ids: its states find the first batch's
    entries (equal returns do not shift them), so every replayed hit is foreign."""
    _side, stats, foreign = _insert_two_batches(seeds=(0, 0))
    assert stats[1]["memory/insert_hit_rate"] > 0.99  # (a few keys were shifted away within batch 1)
    assert foreign > 0.9


def test_the_literal_reading_never_merges_real_states() -> None:
    side, stats, foreign = _insert_two_batches(
        "algo.memory.delta_rule=literal", "algo.memory.neighbourhood=ball"
    )
    assert side.tolerance == pytest.approx(1.3e-3)
    assert [s["memory/insert_hits"] for s in stats] == [0.0, 0.0] and foreign == 0.0
