"""Greedy one-step baseline, decentralised: each UAV sees only its own observation.

Each UAV moves to the neighbouring cell of highest m(U) in its own fused belief (r1), keeping clear of
visible no-fly zones (r3) and visible UAVs' cells (r4). It is the myopic reference for a learned policy."""

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
    """Take the allowed move with the best score: m(U) of the destination - SAFETY_PENALTY * (violations
    there).

    A violation is what r3 or r4 would charge at the destination under the scenario's ``safety_rule``, read
    from the observation's relative positions. Ties within 1e-6 are broken with the seeded generator."""

    def __init__(self, config: EnvConfig, seed: int = 0) -> None:
        super().__init__(config, seed)
        self.moves = torch.tensor(MOVES, dtype=torch.int64, device=torch.device(config.device))

    def _violations(self, features: torch.Tensor, radius: float) -> torch.Tensor:
        """Count, per move ``[E, N, 8]``, the visible entities the reward would charge at its destination."""
        offset, visible = self.layout.relative_cells(features)  # [E, N, K, 2], [E, N, K]
        moves = self.moves.to(offset.device)
        squared = (
            (offset.unsqueeze(-3) - moves.view(8, 1, 2)).to(torch.float32).pow(2).sum(-1)
        )  # [E, N, 8, K]
        return (self.config.violates(squared, radius) & visible.unsqueeze(-2)).sum(-1)

    def scores(self, observation: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Return ``[E, N, 8]`` move scores; masked moves score -inf."""
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
