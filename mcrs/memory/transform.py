"""A TorchRL replay-buffer transform that attaches the episodic memory's answers to training batches.

``ReplayBuffer.sample()`` runs its transforms on the sampled batch, so
``buffer.append_transform(EpisodicLookup(memory, T))`` looks up every transition ``t -> t+1`` with the
current embedding and keys. Any replay buffer of episodes ``[B, T+1]`` with a state key works."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.envs import Transform


class EpisodicLookup(Transform):
    """Write the memory's answer for each transition ``t`` of an episode batch ``[B, T+1]``.

    - ``memory_return`` ``[B, T+1, 1]``: H(phi(s_{t+1}, (t+1)/T)), 0 without a memory within delta; -
    ``memory_hit`` ``[B, T+1]``: whether a stored key lies within delta; - ``memory_ratio`` ``[B, T+1, 1]``
    with ``with_ratio=True`` (EMU): N_xi / N_call of the entry found.

    The last row has no transition and never hits. When the batch carries episode ids (``episode_key``),
    the transform also counts hits on entries written by another episode, since only those add to a
    trajectory's own return.

    Args:
        memory: an :class:`~mcrs.memory.EpisodicMemory`.
        max_steps: the episode length T.
        state_key: where the batch keeps the states ``s_0 .. s_T``.
        with_ratio: also write EMU's desirability ratio.
        episode_key: where the batch may keep the episode ids.
    """

    def __init__(
        self,
        memory,
        max_steps: int,
        state_key: NestedKey = "state",
        with_ratio: bool = False,
        episode_key: NestedKey = "episode",
    ):
        out_keys: list[NestedKey] = ["memory_return", "memory_hit"] + (["memory_ratio"] if with_ratio else [])
        super().__init__(in_keys=[state_key], out_keys=out_keys)
        if max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {max_steps}")
        self.memory, self.max_steps = memory, int(max_steps)
        self.state_key, self.with_ratio, self.episode_key = state_key, with_ratio, episode_key
        self._counts = torch.zeros(3, dtype=torch.int64)  # look-ups, hits, foreign hits

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        state = tensordict.get(self.state_key)
        if state.dim() != 3:
            raise ValueError(
                f"EpisodicLookup expects episodes [B, T+1, state_dim] under {self.state_key!r}, "
                f"got shape {tuple(state.shape)}"
            )
        B, T1 = state.shape[:2]
        time = torch.arange(1, T1, device=state.device, dtype=torch.float32).div_(self.max_steps)
        value, hit, slot = self.memory.lookup(state[:, 1:], time.expand(B, -1))
        pad = value.new_zeros(B, 1)
        tensordict.set("memory_return", torch.cat([value, pad], 1).unsqueeze(-1))
        tensordict.set("memory_hit", torch.cat([hit, hit.new_zeros(B, 1)], 1))
        if self.with_ratio:
            ratio = torch.where(hit, self.memory.desirable_ratio(slot.clamp(min=0)), torch.zeros_like(value))
            tensordict.set("memory_ratio", torch.cat([ratio, pad], 1).unsqueeze(-1))
        episode = tensordict.get(self.episode_key, None)
        if episode is not None:
            foreign = hit & (self.memory.written_by(slot) != episode[:, 1:].to(slot.device))
            self._counts += torch.stack([torch.tensor(hit.numel()), hit.sum().cpu(), foreign.sum().cpu()])
        return tensordict

    def pop_statistics(self) -> dict[str, float]:
        """Return ``lookup_hit_rate`` and ``foreign_hit_rate`` since the last call; empty if none."""
        lookups, hits, foreign = self._counts.tolist()
        self._counts.zero_()
        if not lookups:
            return {}
        return {"lookup_hit_rate": hits / lookups, "foreign_hit_rate": foreign / lookups}

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        return tensordict  # nothing to do when episodes are written

    def __repr__(self) -> str:
        return f"{type(self).__name__}(max_steps={self.max_steps}, with_ratio={self.with_ratio})"
