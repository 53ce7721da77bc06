"""The policy interface of the heuristics, usable wherever TorchRL expects a policy.

A policy reads a batched MCRS tensordict ``[E]`` and writes ``("agents", "action")`` ``[E, N]`` int64. As a
:class:`~tensordict.nn.TensorDictModuleBase` it works with ``env.rollout`` and TorchRL collectors. Each
policy owns a seeded ``torch.Generator``, so the same seed and tensordicts give the same actions."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from mcrs.env.config import EnvConfig
from mcrs.env.layout import ObservationLayout

OBSERVATION = ("agents", "observation")
ACTION_MASK = ("agents", "action_mask")
ACTION = ("agents", "action")


class Policy(TensorDictModuleBase):
    """Base class: subclasses implement :meth:`act`, batched over envs and agents."""

    def __init__(self, config: EnvConfig, seed: int = 0) -> None:
        super().__init__()
        self.in_keys = [OBSERVATION, ACTION_MASK, "step_count"]
        self.out_keys = [ACTION]
        self.config = config
        self.layout = ObservationLayout.from_config(config)
        self.generator = torch.Generator(device=config.device)
        self.generator.manual_seed(int(seed))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = self.act(tensordict)
        tensordict.set(ACTION, action.to(torch.int64))
        return tensordict

    def act(self, tensordict: TensorDictBase) -> torch.Tensor:
        """Return ``[E, N]`` int64 actions, each allowed by ``("agents", "action_mask")``."""
        raise NotImplementedError

    def _random_keys(self, shape: torch.Size, device: torch.device) -> torch.Tensor:
        """Draw uniform keys from the policy's own generator and move them to ``device``."""
        return torch.rand(shape, generator=self.generator, device=self.generator.device).to(device)

    def _uniform_among(self, candidates: torch.Tensor) -> torch.Tensor:
        """Return the index of a uniformly drawn True entry along the last dim; every row must have one."""
        keys = self._random_keys(candidates.shape, candidates.device)
        return torch.where(candidates, keys, -1.0).argmax(-1)
