"""Checkpoints: written atomically, read with ``weights_only=True`` so that no code runs while loading.

A checkpoint is a plain dict of tensors, numbers, strings and nested dicts, marked by ``FORMAT`` and
``VERSION``. Each top-level entry has a SHA-256 of its data (``checksum``), checked before use, because torch
does not check a zip member's CRC.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import torch

from mcrs.experiment.run.history import BEFORE_CALLBACKS_REFUSAL, before_callbacks, current_config
from mcrs.experiment.run.rundir import first_difference
from mcrs.experiment.util.untrusted import check_archive

FORMAT = "mcrs-checkpoint"
VERSION = 1
LAST = "last.pt"


#: The hash of each entry's data (``checksum.entries``).
CHECKSUM = "sha256"
#: Folders already logged as holding unverified checkpoints (history.OLD_FORMS["no checksum"]).
_UNVERIFIED: set[Path] = set()


class CheckpointError(ValueError):
    """A file that is not a usable mcrs checkpoint."""


def digest(value: Any) -> str:
    """SHA-256 of ``value``'s data: tensors' dtype, shape and bytes, other values' type and ``repr``, in
    order."""
    sha = hashlib.sha256()
    _feed(sha, value)
    return sha.hexdigest()


def _feed(sha: Any, value: Any) -> None:
    if isinstance(value, torch.Tensor):
        tensor = value.detach()
        sha.update(f"T{tensor.dtype}{tuple(tensor.shape)};".encode())
        if tensor.numel():
            flat = tensor.cpu().contiguous().reshape(-1)
            sha.update(flat.view(torch.uint8).numpy().data)
    elif isinstance(value, Mapping):
        sha.update(b"{")
        for key, item in value.items():
            _feed(sha, key)
            _feed(sha, item)
        sha.update(b"}")
    elif isinstance(value, (list, tuple)):
        sha.update(b"[" if isinstance(value, list) else b"(")
        for item in value:
            _feed(sha, item)
        sha.update(b"]")
    else:
        sha.update(f"{type(value).__name__}:{value!r};".encode())


def verify(state: Mapping[str, Any], path: str | Path, entries: Any = None) -> None:
    """Check ``entries`` of ``state`` (all by default) against the checksum; refuse a damaged entry naming it."""
    path = Path(path)
    checksum = state.get("checksum")
    if checksum is None:  # history.OLD_FORMS["no checksum"]
        if path.parent not in _UNVERIFIED:
            _UNVERIFIED.add(path.parent)
            logging.getLogger("mcrs.run").info(
                "%s was written before checksums existed: its data is read unverified (as are the other "
                "such files in %s)",
                path,
                path.parent,
            )
        return
    expected = checksum.get("entries") if isinstance(checksum, Mapping) else None
    if not isinstance(expected, Mapping) or checksum.get("algorithm") != CHECKSUM:
        raise CheckpointError(f"checkpoint {path}: entry checksum: not a {CHECKSUM} checksum of its entries")
    names = [k for k in state if k != "checksum"] if entries is None else list(entries)
    for name in [*names, *(k for k in expected if entries is None and k not in state)]:
        if name not in state:
            raise CheckpointError(f"checkpoint {path}: entry {name}: in its checksum but not in the file")
        if name not in expected:
            raise CheckpointError(f"checkpoint {path}: entry {name}: not covered by its checksum: refused")
        if digest(state[name]) != expected[name]:
            raise CheckpointError(
                f"checkpoint {path}: entry {name}: its data does not match the checksum written with it: "
                "the file is damaged; refused (use an earlier checkpoint or run again)"
            )


def save_atomic(payload: dict[str, Any], path: str | Path) -> Path:
    """Write ``payload`` to ``path`` so that a crash leaves either the old file or the new one, never half."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path.parent)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            writer = _Writer(handle)
            whole = {"format": FORMAT, "version": VERSION, **payload}
            whole["checksum"] = {"algorithm": CHECKSUM, "entries": {k: digest(v) for k, v in whole.items()}}
            try:
                torch.save(whole, writer)
            except RuntimeError:  # torch reports a failed write as "unexpected pos": give the OS's reason
                if writer.error is not None:
                    raise writer.error from None
                raise
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


class _Writer:
    """A file for ``torch.save`` that keeps a failed write's ``OSError``, which torch hides."""

    def __init__(self, handle: Any) -> None:
        self.handle, self.error = handle, None

    def write(self, data: bytes) -> int:
        try:
            return self.handle.write(data)
        except OSError as error:
            self.error = self.error or error
            raise

    def flush(self) -> None:
        self.handle.flush()


def remove_stale_temporaries(directory: str | Path) -> list[Path]:
    """Delete temporaries left by a writer killed mid-save; a run saves from one process, one file at a time."""
    stale = list(Path(directory).glob(".*.pt.*.tmp"))
    for tmp in stale:
        tmp.unlink(missing_ok=True)
    return stale


def load(
    path: str | Path,
    map_location: str | torch.device = "cpu",
    mmap: bool = False,
    verify_data: bool | None = None,
) -> dict[str, Any]:
    """Read a checkpoint without executing code; refuse anything that is not ours. ``mmap=True`` maps the
    tensors instead of reading them; ``verify_data`` defaults to checking every entry unless mapped."""
    path = Path(path)
    try:
        if not path.is_file():
            raise CheckpointError(f"checkpoint {path} does not exist")
        if path.stat().st_size == 0:
            raise CheckpointError(f"checkpoint {path} cannot be read safely: the file is empty")
        refused = check_archive(path)  # before torch.load: a zip bomb is refused from its directory
    except OSError as error:  # an unreadable file or directory
        raise CheckpointError(f"checkpoint {path} cannot be read: {error.strerror or error}") from None
    if refused is not None:
        raise CheckpointError(f"checkpoint {path} cannot be read safely: {refused}")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True, mmap=mmap)
    except Exception as error:  # truncated, corrupt or carrying objects that need code to load
        raise CheckpointError(
            f"checkpoint {path} cannot be read safely: {_unreadable_reason(error)}"
        ) from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not an mcrs checkpoint (no '{FORMAT}' marker)")
    if payload.get("version") != VERSION:
        raise CheckpointError(
            f"{path} has checkpoint version {payload.get('version')}; this mcrs reads {VERSION}"
        )
    check = not mmap if verify_data is None else verify_data
    if check:
        verify(payload, path)
    return payload


def _unreadable_reason(error: Exception) -> str:
    """One line on why ``torch.load(weights_only=True)`` refused a file."""
    text = re.sub(r"\x1b\[[0-9;]*m", "", str(error))
    blocked = re.search(r"unsupported GLOBAL (\S+) whose module (\S+) is blocked", text)
    if blocked:  # torch's text advises weights_only=False: we never load a checkpoint that way
        return f"it needs code to load ({blocked.group(1)}, from the blocked module {blocked.group(2)}); refused without running it"
    if "WeightsUnpickler error:" in text:
        detail = text.split("WeightsUnpickler error:", 1)[1].strip().splitlines()[0]
        detail = detail.split(" was not an allowed global")[0].strip()
        if detail.startswith("Unsupported global"):
            return f"it needs code to load ({detail}); refused without running it"
        return f"it is corrupt or not a torch file ({detail})"
    if "PytorchStreamReader" in text:
        return f"it is truncated or corrupt ({text.split('.')[0]})"
    # the first line that is not torch's advice to load unsafely
    lines = [line for line in text.strip().splitlines() if line.strip() and "weights_only" not in line]
    return f"{type(error).__name__}: {lines[0] if lines else 'it cannot be loaded with weights_only=True'}"


def checkpoint_path(run_dir: str | Path, name: str = LAST) -> Path:
    return Path(run_dir) / "checkpoints" / name


#: Dotted paths into ``last.pt`` of the bulk only resuming needs: the replay and the episodic memory's entries
#: (its embedding weights stay). ``episodic.memory`` is history.OLD_FORMS["before callbacks"].
BULK = ("replay", "replay_blocks", "callbacks.memory.memory", "episodic.memory")


def prune_bulk(run_dir: str | Path) -> tuple[int, int]:
    """Drop :data:`BULK` from ``run_dir``'s ``last.pt`` atomically; the run can no longer be resumed. Returns
    the file's size before and after."""
    path = checkpoint_path(run_dir)
    before = path.stat().st_size if path.is_file() else 0
    state = load(path, mmap=True)  # the bulk is mapped, never read into memory
    # what is kept is written with a new checksum: it is checked first (the entries dropped whole are not)
    verify(state, path, [k for k in state if k != "checksum" and k not in BULK])
    dropped = []
    for dotted in BULK:
        *parents, last = dotted.split(".")
        node = state
        for part in parents:
            node = node.get(part) if isinstance(node, dict) else None
        if isinstance(node, dict) and last in node:
            del node[last]
            dropped.append(dotted)
    if not dropped:
        return before, before
    state["pruned"] = {"dropped": dropped, "bytes_before": before}
    state = {k: v for k, v in state.items() if k not in ("format", "version", "checksum")}
    save_atomic(state, path)
    if "replay_blocks" in dropped:  # the block files beside last.pt (mcrs.experiment.run.replay_store)
        for block in path.parent.glob("replay_*_*.pt"):
            block.unlink(missing_ok=True)
    return before, path.stat().st_size


def refuse_pre_release(state: dict[str, Any], path: str | Path) -> dict[str, Any]:
    """``state``, unless its layout is from before callbacks (history.OLD_FORMS["before callbacks"])."""
    if before_callbacks(state):
        raise CheckpointError(f"{path} {BEFORE_CALLBACKS_REFUSAL}")
    return state


def awaits_final_evaluation(state: Mapping[str, Any]) -> bool:
    """Whether a ``last.pt`` was saved after the last collector batch but before the final evaluation, which a
    kill can leave."""
    counters = state.get("counters")
    step = state.get("last_eval_step", -1)
    if not isinstance(counters, Mapping) or step == -1:
        return False
    return step != counters.get("env_steps")


def weights_path(run_dir: str | Path, env_steps: int) -> Path:
    """``checkpoints/model_<steps>.pt``: the policy's weights at ``env_steps``."""
    return checkpoint_path(run_dir, f"model_{env_steps:09d}.pt")


def prune_weights(run_dir: str | Path, keep: int) -> list[Path]:
    """Delete all but the newest ``keep`` weight files (0 keeps all); returns them."""
    if keep <= 0:
        return []
    files = sorted(checkpoint_path(run_dir).parent.glob("model_*.pt"))  # zero-padded steps sort in order
    stale = files[:-keep]
    for path in stale:
        path.unlink(missing_ok=True)
    return stale


def load_resumable(
    path: Path,
    expected: dict[str, Any],
    fingerprint_of: Callable[[dict[str, Any], dict[str, Any]], dict[str, Any]],
    map_location: str | torch.device,
    advice: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """``path``'s state, if it can resume the run whose fingerprint is ``expected``. ``fingerprint_of(config,
    learner)`` derives a missing fingerprint; ``advice[field]`` ends a refusal on ``field``."""
    state = refuse_pre_release(load(path, map_location=map_location), path)
    saved = state.get("fingerprint")
    if saved is None:  # history.OLD_FORMS["no fingerprint"]
        saved = fingerprint_of(current_config(state.get("config", {})), state.get("learner", {}))
    difference = first_difference(saved, expected)
    if difference is not None:
        hint = (advice or {}).get(difference.split(":", 1)[0], "")
        raise CheckpointError(f"{path} does not belong to this run: {difference}{hint}")
    if "replay" not in state and "replay_blocks" not in state:
        raise CheckpointError(
            f"{path} has no replay buffer (train.save_replay=false): it holds weights, not a resumable run"
        )
    return state
