"""The checkpoint format of :class:`~mcrs.memory.episodic.EpisodicMemory`: its ``state_dict`` and
``load_state_dict``.

The format is a contract with checkpoints on disk, so it lives apart from Algorithm 1. The functions take
the memory as an argument and do not import its module, which imports them."""

from __future__ import annotations

from typing import Any

import torch

STATE_VERSION = 2  # 2: the writing episode of every entry
UNKNOWN_EPISODE = -1  # the episode id of an entry written without one (and of every free slot)


def memory_state(memory: Any) -> dict[str, Any]:
    """Return the filled part of ``memory`` (oldest first), the ring position, the statistics and the codec's
    identity. It holds only plain types, so ``torch.load(weights_only=True)`` reads it."""
    slots = memory.live_slots()
    state: dict[str, Any] = {
        "version": STATE_VERSION,
        "codec": memory.codec.identity(),
        "key_dim": memory.key_dim,
        "delta": memory.tolerance,  # the match tolerance, under the name the format has always used
        "capacity": memory.capacity,
        "start": memory.start,
        "size": memory.size,
        "stats_size": memory.stats_size,
        "mean": memory.index.mean.cpu(),
        "std": memory.index.std.cpu(),
        "track_desirability": memory.track_desirability,
    }
    state.update({name: values[slots].cpu() for name, values in memory.columns().items()})
    return state


def restore_memory(memory: Any, state: dict[str, Any]) -> None:
    """Restore a :func:`memory_state` into ``memory``, refusing one from another map or key_dim, or one that
    does not fit."""
    if state.get("version") != STATE_VERSION:
        raise ValueError(f"episodic memory state version {state.get('version')!r}, expected {STATE_VERSION}")
    mismatch = memory.codec.identity_mismatch(state["codec"])
    if mismatch:
        raise ValueError(f"episodic memory saved for another map or sensor model ({mismatch})")
    if state["key_dim"] != memory.key_dim:
        raise ValueError(
            f"episodic memory saved with key_dim={state['key_dim']}, this one has key_dim={memory.key_dim}"
        )
    size = int(state["size"])
    if size > memory.capacity:
        raise ValueError(f"episodic memory holds {size} entries, more than capacity={memory.capacity}")
    if memory.track_desirability and not state["track_desirability"]:
        raise ValueError("episodic memory saved without desirability counters (EMU) cannot restore them")
    start = int(state["start"]) if state["capacity"] == memory.capacity else 0
    dev = memory.device
    memory.live.zero_()
    memory.episode.fill_(UNKNOWN_EPISODE)
    memory.start, memory.size = start, size
    slots = memory.live_slots()
    memory.codes = torch.empty(
        memory.capacity, *memory.codes.shape[1:], dtype=state["codes"].dtype, device=dev
    )
    for name, values in memory.columns().items():
        values[slots] = state[name].to(dev, values.dtype)
    memory.live[slots] = True
    memory.index.mean = state["mean"].to(dev, torch.float32)
    memory.index.std = state["std"].to(dev, torch.float32)
    memory.stats_size = int(state["stats_size"])
    memory.rebuild_index(refresh=False)
