"""A run's progress counters (saved in every checkpoint) and the seed of each collector batch."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class Counters:
    """Progress of a run, saved in every checkpoint."""

    env_steps: int = 0
    episodes: int = 0
    updates: int = 0
    iteration: int = 0  # collector batches
    update_credit: float = 0.0  # fractional learner updates owed (updates_per_episode < 1)
    next_target_update: int = 0  # episode count at which the target networks are next copied
    next_eval: int = 0
    next_checkpoint: int = 0
    next_log: int = 0


def batch_seed(seed: int, iteration: int) -> int:
    """Seed of the environments of collector batch ``iteration``: a reproducible stream per run."""
    return (seed * 1_000_003 + iteration) % (2**63)
