"""Specs the batched task envs share: one agent group's discrete actions and the done keys.

Each task env names its own group and observation spec; the action and done specs are the same shape
for all of them, so they are built here once.
"""

from __future__ import annotations

import torch
from torchrl.data import Categorical, Composite


def group_action_spec(
    group: str, num_envs: int, n_agents: int, n_actions: int, device: torch.device | str | None
) -> Composite:
    """``(group, "action")``: one of ``n_actions`` per agent, batched over ``num_envs`` envs."""
    return Composite(
        {
            group: Composite(
                action=Categorical(n_actions, shape=(num_envs, n_agents), dtype=torch.int64, device=device),
                shape=(num_envs, n_agents),
                device=device,
            )
        },
        shape=(num_envs,),
        device=device,
    )


def done_spec(num_envs: int, device: torch.device | str | None) -> Composite:
    """``done``, ``terminated`` and ``truncated``: one flag per env."""
    done = Categorical(2, shape=(num_envs, 1), dtype=torch.bool, device=device)
    return Composite(
        done=done, terminated=done.clone(), truncated=done.clone(), shape=(num_envs,), device=device
    )
