"""Uniform random baseline: the floor any learned or hand-made policy should beat."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from mcrs.policies.base import ACTION_MASK, Policy


class RandomPolicy(Policy):
    """Each UAV draws uniformly and independently among its allowed moves."""

    def act(self, tensordict: TensorDictBase) -> torch.Tensor:
        return self._uniform_among(tensordict.get(ACTION_MASK))
