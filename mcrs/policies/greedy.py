"""Greedy one-step baseline: decentralised, each UAV sees only its own observation.

It moves to the neighbouring cell of highest m(U) in its own fused belief (the largest immediate
uncertainty reduction, reward r1), while keeping clear of visible no-fly zones (r3) and of the current
cells of visible UAVs (r4). It is the natural myopic reference for a learned policy.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from mcrs.env.config import EnvConfig
from mcrs.env.core import MOVES
from mcrs.policies.base import ACTION_MASK, OBSERVATION, Policy

# Per safety violation; larger than any belief gain (m(U) <= 1), so safety always comes first.
SAFETY_PENALTY = 10.0
TIE_TOLERANCE = 1e-6


class GreedyPolicy(Policy):
    """Score of a move = m(U) of its destination - SAFETY_PENALTY * (violations there); best allowed move.

    A violation is what r3 or r4 would charge at the destination: a visible no-fly zone closer than
    ``no_fly_safety`` (d1) or a visible other UAV's current cell closer than ``uav_safety`` (d2) under the
    scenario's ``safety_rule`` (``near``: within), from the relative-position features of the observation.
    Ties (within 1e-6) are broken uniformly with the policy's seeded generator.
    """

    def __init__(self, config: EnvConfig, seed: int = 0) -> None:
        super().__init__(config, seed)
        self.moves = torch.tensor(MOVES, dtype=torch.int64, device=torch.device(config.device))

    def _violations(self, features: torch.Tensor, radius: float) -> torch.Tensor:
        """``[E, N, 8]``: visible entities that the reward would charge at each move's destination."""
        offset, visible = self.layout.relative_cells(features)  # [E, N, K, 2], [E, N, K]
        moves = self.moves.to(offset.device)
        squared = (
            (offset.unsqueeze(-3) - moves.view(8, 1, 2)).to(torch.float32).pow(2).sum(-1)
        )  # [E, N, 8, K]
        return (self.config.violates(squared, radius) & visible.unsqueeze(-2)).sum(-1)

    def scores(self, observation: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """``[E, N, 8]`` move scores; masked moves score -inf."""
        layout, c = self.layout, self.config
        gain = layout.unknown_by_action(observation)
        violations = self._violations(layout.no_fly_features(observation), c.no_fly_safety)
        if layout.n_others:
            violations = violations + self._violations(layout.uav_features(observation), c.uav_safety)
        score = gain - SAFETY_PENALTY * violations
        return score.masked_fill(~mask, float("-inf"))

    def act(self, tensordict: TensorDictBase) -> torch.Tensor:
        mask = tensordict.get(ACTION_MASK)
        score = self.scores(tensordict.get(OBSERVATION), mask)
        best = score.amax(-1, keepdim=True)
        return self._uniform_among((score >= best - TIE_TOLERANCE) & mask)
