"""The replay buffer saved incrementally, in blocks of slots beside ``last.pt``.

A full map20 replay is about 3.3 GB, too much to write into every checkpoint. Its slots are cut into blocks,
one file each (``checkpoints/replay_<block>_<generation>.pt``), and a save rewrites only the blocks written
since the last one; ``last.pt`` carries their manifest. New blocks get new names, ``last.pt`` is written
atomically, and then :meth:`ReplayStore.commit` deletes the files no longer named, so a crash leaves the
previous ``last.pt`` whole.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import ReplayBuffer

from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.run.rundir import first_difference

#: How nested keys are written in a saved replay: ``("agents", "observation")`` as ``"agents/observation"``.
KEY_SEPARATOR = "/"


def flat_episodes(episodes: TensorDictBase) -> dict[str, torch.Tensor]:
    """``episodes`` as a flat ``{"agents/observation": tensor}`` dict, the form checkpoints store. Unlike
    ``ReplayBuffer.state_dict()``, only the episodes given are written."""
    return dict(episodes.flatten_keys(KEY_SEPARATOR).items())


def episodes_from_flat(flat: dict[str, torch.Tensor], batch_size: Sequence[int]) -> TensorDict:
    """The inverse of :func:`flat_episodes`."""
    return TensorDict(flat, batch_size=list(batch_size)).unflatten_keys(KEY_SEPARATOR)


def replay_state_dict(buffer: ReplayBuffer) -> dict:
    """The filled part of the storage and the writer's position."""
    n = len(buffer)
    state: dict = {"length": n, "writer": buffer.writer.state_dict()}
    if n:
        episodes = buffer.storage.get(torch.arange(n))
        state["batch_size"] = list(episodes.batch_size)
        state["episodes"] = flat_episodes(episodes)
    return state


def load_replay_state_dict(buffer: ReplayBuffer, state: dict) -> None:
    """Refill an empty buffer from :func:`replay_state_dict`: same slots, same next write position."""
    if len(buffer):
        raise ValueError("load_replay_state_dict needs an empty buffer")
    n = int(state["length"])
    if n:
        if n > len(buffer.storage) and buffer.storage.max_size < n:
            raise ValueError(f"the saved replay holds {n} episodes, more than this buffer's capacity")
        episodes = episodes_from_flat(state["episodes"], state["batch_size"])
        buffer.extend(episodes.to(buffer.storage.device) if buffer.storage.device is not None else episodes)
    buffer.writer.load_state_dict(state["writer"])


BLOCK_EPISODES = 100  # slots per block file (map20: about 66 MB)
_BLOCK_FILE = re.compile(r"^replay_\d+_\d+\.pt$")


class ReplayStore:
    """Tracks the slots written since the last save and writes only their blocks to ``directory``."""

    def __init__(self, directory: str | Path, block_episodes: int = BLOCK_EPISODES) -> None:
        if block_episodes < 1:
            raise ValueError(f"block_episodes must be >= 1, got {block_episodes}")
        self.directory = Path(directory)
        self.block_episodes = int(block_episodes)
        self.files: list[str] = []  # file of each block, as the last committed manifest names them
        self.generation = 0
        self._dirty: set[int] = set()
        self._pending: list[str] | None = None

    def mark_written(self, index: torch.Tensor) -> None:
        """Record the storage slots that ``ReplayBuffer.extend`` returned."""
        blocks = torch.unique(index.reshape(-1).to("cpu", torch.long) // self.block_episodes)
        self._dirty.update(int(b) for b in blocks)

    def save(self, buffer: ReplayBuffer, fingerprint: dict[str, Any] | None = None) -> dict[str, Any]:
        """Write the blocks changed since the last commit, each with the run's ``fingerprint``; returns the
        manifest."""
        n = len(buffer)
        n_blocks = math.ceil(n / self.block_episodes)
        self.generation += 1
        files = self.files[:n_blocks] + [""] * max(0, n_blocks - len(self.files))
        for block in range(n_blocks):
            if files[block] and block not in self._dirty:
                continue
            lo, hi = block * self.block_episodes, min(n, (block + 1) * self.block_episodes)
            episodes = buffer.storage.get(torch.arange(lo, hi))
            name = f"replay_{block:05d}_{self.generation:06d}.pt"
            ckpt.save_atomic(
                {
                    "replay_block": block,
                    "fingerprint": fingerprint,
                    "batch_size": list(episodes.batch_size),
                    "episodes": flat_episodes(episodes.cpu()),
                },
                self.directory / name,
            )
            files[block] = name
        self._pending = files
        return {
            "length": n,
            "writer": buffer.writer.state_dict(),
            "block_episodes": self.block_episodes,
            "generation": self.generation,
            "files": list(files),
            "fingerprinted": fingerprint is not None,
        }

    def commit(self) -> None:
        """Delete the files the new manifest no longer names, once ``last.pt`` naming it is on disk."""
        if self._pending is None:
            return
        self.files, self._pending = self._pending, None
        self._dirty.clear()
        keep = set(self.files)
        for path in self.directory.glob("replay_*.pt"):
            if _BLOCK_FILE.match(path.name) and path.name not in keep:
                path.unlink(missing_ok=True)

    def load(
        self, buffer: ReplayBuffer, manifest: dict[str, Any], fingerprint: dict[str, Any] | None = None
    ) -> None:
        """Refill an empty ``buffer`` from a manifest, checking each block's index and fingerprint."""
        if len(buffer):
            raise ValueError("ReplayStore.load needs an empty buffer")
        check_manifest(manifest)
        if int(manifest["block_episodes"]) != self.block_episodes:
            raise ckpt.CheckpointError(
                f"the saved replay has blocks of {manifest['block_episodes']} episodes, this run "
                f"{self.block_episodes}"
            )
        n = int(manifest["length"])
        if n > buffer.storage.max_size:
            raise ValueError(f"the saved replay holds {n} episodes, more than this buffer's capacity")
        for block, name in enumerate(manifest["files"]):
            path = self.directory / name
            payload = ckpt.load(path, mmap=True, verify_data=True)  # its episodes are used: checked
            if payload.get("replay_block") != block:
                raise ckpt.CheckpointError(
                    f"{path} is not block {block} of this run's replay (it says {payload.get('replay_block')!r})"
                )
            # history.OLD_FORMS["unfingerprinted replay blocks"]
            if manifest.get("fingerprinted") and fingerprint is not None:
                saved = payload.get("fingerprint")
                difference = (
                    "it carries none" if not isinstance(saved, dict) else first_difference(saved, fingerprint)
                )
                if difference is not None:
                    raise ckpt.CheckpointError(f"{path} does not belong to this run: {difference}")
            episodes = episodes_from_flat(payload["episodes"], payload["batch_size"])
            device = buffer.storage.device
            buffer.extend(episodes.to(device) if device is not None else episodes)
        if len(buffer) != n:
            raise ckpt.CheckpointError(
                f"the replay files in {self.directory} hold {len(buffer)} episodes, the manifest {n}"
            )
        buffer.writer.load_state_dict(manifest["writer"])
        self.files = list(manifest["files"])
        self.generation = int(manifest["generation"])
        self._dirty.clear()


def check_manifest(manifest: Any) -> None:
    """Check a ``replay_blocks`` manifest: whole numbers >= 0 and plain block file names, never
    ``../other_run``."""
    if not isinstance(manifest, dict):
        raise ckpt.CheckpointError("entry replay_blocks: not a mapping")
    for key in ("length", "block_episodes", "generation"):
        value = manifest.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ckpt.CheckpointError(f"entry replay_blocks.{key}: {value!r} is not a whole number >= 0")
    files = manifest.get("files")
    if not isinstance(files, list):
        raise ckpt.CheckpointError("entry replay_blocks.files: not a list of file names")
    for k, name in enumerate(files):
        if not isinstance(name, str) or not _BLOCK_FILE.match(name):
            raise ckpt.CheckpointError(
                f"entry replay_blocks.files[{k}]: {name!r} is not a block file of this run "
                "(replay_<block>_<generation>.pt in its checkpoints/ folder): refused"
            )
