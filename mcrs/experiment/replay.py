"""Whole episodes in a TorchRL replay buffer.

A collector batch ``[E, T]`` (TorchRL layout: ``("next", key)`` holds step t+1) becomes ``E`` items of the
*episode layout* ``[T + 1]`` read by :class:`~mcrs.objectives.ValueFactorisationLoss`: observations,
masks and states for steps ``0..T`` (each stored once, not twice as root and ``"next"``), actions, rewards
and done flags for transitions ``0..T-1`` with one padding row. pymarl stores episodes the same way.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import LazyTensorStorage, RandomSampler, ReplayBuffer

#: Keys read at every step (kept for steps 0..T).
STEP_KEYS: tuple[NestedKey, ...] = (("agents", "observation"), ("agents", "action_mask"), "state")


def episodes_from_rollout(
    batch: TensorDictBase,
    step_keys: Sequence[NestedKey] = STEP_KEYS,
    action_key: NestedKey = ("agents", "action"),
    reward_key: NestedKey = "reward",
) -> TensorDict:
    """Convert a collector batch ``[E, T]`` of whole episodes into the episode layout ``[E, T + 1]``.

    Every row must be one complete episode: it starts after a reset and its last step is done. Our
    environment guarantees this when ``frames_per_batch = num_envs * max_steps``.
    """
    if batch.batch_dims != 2:
        raise ValueError(
            f"expected a collector batch [num_envs, T], got batch_size {tuple(batch.batch_size)}"
        )
    done = batch.get(("next", "done"))
    if not bool(done[:, -1].all()):
        raise ValueError(
            "every row of the batch must end with a finished episode: set frames_per_batch to "
            "num_envs * max_steps so that collection stays aligned with episodes"
        )
    if "step_count" in batch.keys() and bool((batch.get("step_count")[:, 0] != 0).any()):  # noqa: SIM118
        raise ValueError("every row of the batch must start with a reset (step_count 0)")
    E, T = batch.batch_size
    out = TensorDict(batch_size=[E, T + 1], device=batch.device)
    for key in step_keys:
        out.set(key, torch.cat([batch.get(key), batch.get(("next", key))[:, -1:]], dim=1))

    def padded(value: torch.Tensor, fill: float | bool = 0) -> torch.Tensor:
        return torch.cat([value, torch.full_like(value[:, :1], fill)], dim=1)

    out.set(action_key, padded(batch.get(action_key)))
    out.set("reward", padded(batch.get(("next", reward_key))))
    out.set("done", padded(done, True))
    out.set("terminated", padded(batch.get(("next", "terminated")), False))
    filled = torch.ones(E, T + 1, dtype=torch.bool, device=batch.device)
    filled[:, -1] = False
    out.set("filled", filled)
    return out


def make_episode_buffer(capacity: int, batch_size: int, device: str | torch.device = "cpu") -> ReplayBuffer:
    """A replay buffer of whole episodes: uniform sampling, the oldest episode is overwritten when full."""
    if capacity < 1:
        raise ValueError(f"replay capacity must be >= 1 episode, got {capacity}")
    return ReplayBuffer(
        storage=LazyTensorStorage(capacity, device=device),
        sampler=RandomSampler(),
        batch_size=batch_size,
    )


def replay_state_dict(buffer: ReplayBuffer) -> dict:
    """The stored episodes (only the filled part, not the whole capacity) and the writer's position."""
    n = len(buffer)
    state: dict = {"length": n, "writer": buffer.writer.state_dict()}
    if n:
        episodes = buffer.storage.get(torch.arange(n))
        state["batch_size"] = list(episodes.batch_size)
        state["episodes"] = {
            "/".join(k) if isinstance(k, tuple) else k: v for k, v in episodes.items(True, True)
        }
    return state


def load_replay_state_dict(buffer: ReplayBuffer, state: dict) -> None:
    """Refill an empty buffer from :func:`replay_state_dict`: same slots, same next write position."""
    if len(buffer):
        raise ValueError("load_replay_state_dict needs an empty buffer")
    n = int(state["length"])
    if n:
        if n > len(buffer.storage) and buffer.storage.max_size < n:
            raise ValueError(f"the saved replay holds {n} episodes, more than this buffer's capacity")
        episodes = TensorDict(
            {tuple(k.split("/")): v for k, v in state["episodes"].items()}, batch_size=state["batch_size"]
        )
        buffer.extend(episodes.to(buffer.storage.device) if buffer.storage.device is not None else episodes)
    buffer.writer.load_state_dict(state["writer"])
