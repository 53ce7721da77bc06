"""Whole episodes in a TorchRL replay buffer.

A collector batch ``[E, T]``, where ``("next", key)`` holds step t+1, becomes one item of the *episode layout*
``[T + 1]`` per episode, as pymarl stores them and :class:`~mcrs.objectives.ValueFactorisationLoss` reads
them: observations, masks and states for steps ``0..L`` (each stored once), actions, rewards and done flags
for transitions ``0..L-1``, padded to ``T + 1`` rows and masked by ``filled``.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import LazyTensorStorage, RandomSampler, ReplayBuffer

from mcrs.choices import TIME_LIMITS

#: Keys read at every step (kept for steps 0..T).
STEP_KEYS: tuple[NestedKey, ...] = (("agents", "observation"), ("agents", "action_mask"), "state")


def _require(batch: TensorDictBase, key: NestedKey, origin: str) -> torch.Tensor:
    value = batch.get(key, None)
    if value is None:
        raise KeyError(f"episodes_from_rollout: the collector batch has no {key!r} ({origin})")
    return value


def _episode_ends(
    batch: TensorDictBase, done: torch.Tensor, whole_episodes: bool, first_episode_only: bool
) -> torch.Tensor:
    """``[E, T]``: whether each transition ends an episode piece, after checking the rows against
    ``whole_episodes`` and ``first_episode_only``."""
    E, T = batch.batch_size
    ends = done.reshape(E, T, -1).any(-1)  # the transition ends an episode
    if first_episode_only:
        if not whole_episodes:
            raise ValueError("first_episode_only needs whole_episodes=True (rows that start at a reset)")
        if not bool(ends.any(-1).all()):
            rows = (~ends.any(-1)).nonzero().flatten().tolist()
            raise ValueError(
                f"rows {rows[:8]} of the batch hold no done step: an episode outlasted the batch's "
                f"{T} steps (a task's episodes must end by max_steps: TorchRL's StepCounter(max_steps))"
            )
        ends = ends & (ends.long().cumsum(-1) == 1)  # each row's first end only
        if "step_count" in batch.keys() and bool((batch.get("step_count")[:, 0] != 0).any()):  # noqa: SIM118
            raise ValueError("every row of the batch must start with a reset (step_count 0)")
    elif whole_episodes:
        if not bool(ends[:, -1].all()):
            rows = (~ends[:, -1]).nonzero().flatten().tolist()
            raise ValueError(
                f"rows {rows[:8]} of the batch do not end with a done step: the collector cut an episode. "
                "A recurrent agent needs whole episodes: set frames_per_batch to num_envs * max_steps for a "
                "task of fixed episode length; with a feed-forward agent pass whole_episodes=False, which "
                "keeps the cut piece and bootstraps from it"
            )
        if "step_count" in batch.keys() and bool((batch.get("step_count")[:, 0] != 0).any()):  # noqa: SIM118
            raise ValueError(
                "every row of the batch must start with a reset (step_count 0); with a feed-forward agent "
                "pass whole_episodes=False"
            )
    else:
        ends = ends.clone()
        ends[:, -1] = True  # the batch's cut: done (bootstrap), never terminated
    return ends


def episodes_from_rollout(
    batch: TensorDictBase,
    step_keys: Sequence[NestedKey] = STEP_KEYS,
    action_key: NestedKey = ("agents", "action"),
    reward_key: NestedKey = "reward",
    *,
    whole_episodes: bool = True,
    time_limit: str = "bootstrap",
    first_episode_only: bool = False,
) -> TensorDict:
    """Convert a collector batch ``[E, T]`` into the episode layout ``[M, T + 1]``, one item per episode.

    A row may hold several episodes; each becomes its own item, padded with ``filled`` False, ``done`` True,
    actions and rewards 0, and the step keys repeating its final next step. Per-agent rewards
    (``reward_key=("agents", "reward")``) stay per agent.

    ``whole_episodes=True`` (a recurrent agent) requires every row to start at a reset and end with a done
    step, which the env guarantees when ``frames_per_batch = num_envs * max_steps``. With ``False`` (a
    feed-forward agent) rows may be cut mid-episode; the cut transition is ``done`` but not ``terminated``, so
    its target bootstraps.

    ``time_limit="terminal"`` also marks the truncated transitions ``terminated``, so their targets do not
    bootstrap; ``"bootstrap"`` keeps the env's flags. ``first_episode_only`` keeps each row's first episode
    and drops the steps after it, as pymarl's runners do."""
    if time_limit not in TIME_LIMITS:
        raise ValueError(f"time_limit={time_limit!r}: must be one of {list(TIME_LIMITS)}")
    if batch.batch_dims != 2:
        raise ValueError(
            f"expected a collector batch [num_envs, T], got batch_size {tuple(batch.batch_size)}"
        )
    E, T = batch.batch_size
    done = _require(batch, ("next", "done"), "the env's done flags")
    terminated = _require(batch, ("next", "terminated"), "the env's terminated flags")
    if time_limit == "terminal":
        truncated = _require(
            batch, ("next", "truncated"), "the env's truncated flags (time_limit='terminal')"
        )
        terminated = terminated | truncated
    ends = _episode_ends(batch, done, whole_episodes, first_episode_only)  # [E, T]

    # Items: one per episode piece, in row-major order. starts/ends mark each piece's first/last step.
    starts = torch.zeros_like(ends)
    starts[:, 0] = True
    if not first_episode_only:  # a piece starts after every end; with first_episode_only, only at 0
        starts[:, 1:] = ends[:, :-1]
    row, first = starts.nonzero(as_tuple=True)  # [M]
    last = ends.nonzero(as_tuple=True)[1]  # [M]: the same order, one end per piece
    M, device = row.numel(), batch.device
    p = torch.arange(T + 1, device=ends.device)
    filled = p < (last - first + 1).unsqueeze(-1)  # [M, T+1]
    t = (first.unsqueeze(-1) + p).clamp(max=T - 1)  # source step of every item row (clamped on padding)
    rows = row.unsqueeze(-1).expand(M, T + 1)

    def where(value: torch.Tensor, other: torch.Tensor | float | bool) -> torch.Tensor:
        mask = filled.view(M, T + 1, *([1] * (value.dim() - 2)))
        other = other if isinstance(other, torch.Tensor) else torch.full_like(value, other)
        return torch.where(mask, value, other)

    out = TensorDict(batch_size=[M, T + 1], device=device)
    for key in step_keys:
        origin = "a step key: the env must write it at reset and at every step (step_keys=...)"
        value = _require(batch, key, origin)[rows, t]
        final = _require(batch, ("next", key), origin)[row, last].unsqueeze(1)  # o_L of each item
        out.set(key, where(value, final.expand_as(value)))
    action = _require(batch, action_key, "the policy's action (action_key=...)")
    out.set(action_key, where(action[rows, t], 0))
    reward = _require(
        batch, ("next", reward_key), "the env's reward; per-agent rewards: reward_key=('agents', 'reward')"
    )
    out.set("reward", where(reward[rows, t], 0))
    out.set("done", where(ends.view(E, T, 1)[rows, t].to(done.dtype), True))
    out.set("terminated", where(terminated.reshape(E, T, -1).any(-1, keepdim=True)[rows, t], False))
    out.set("filled", filled)
    return out


def make_episode_buffer(capacity: int, batch_size: int, device: str | torch.device = "cpu") -> ReplayBuffer:
    """A replay buffer of whole episodes with uniform sampling; the oldest episode is overwritten when full."""
    if capacity < 1:
        raise ValueError(f"replay capacity must be >= 1 episode, got {capacity}")
    return ReplayBuffer(
        storage=LazyTensorStorage(capacity, device=device),
        sampler=RandomSampler(),
        batch_size=batch_size,
    )
