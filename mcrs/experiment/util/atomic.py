"""A file written whole or not at all: a reader (a parallel job, a resumed campaign, ``git add``) sees the
old file or the new one, never half of one, and a failed write leaves no temporary behind."""

from __future__ import annotations

import contextlib
import fcntl
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

__all__ = ["ChangedSinceRead", "write_bytes_atomic", "write_if_unchanged", "write_text_atomic"]


class ChangedSinceRead(Exception):
    """A file a tool read, worked on and meant to rewrite was changed meanwhile: nothing is written."""


def write_text_atomic(path: str | Path, text: str) -> Path:
    """:func:`write_bytes_atomic` for text (UTF-8)."""
    return write_bytes_atomic(path, text.encode())


def _temporary(path: Path, data: bytes) -> str:
    """``data`` in a new temporary file of its own beside ``path`` (mkstemp: two writers never share one),
    synced and 0644; its name."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return tmp


def write_bytes_atomic(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file in the same folder, synced, then renamed over
    ``path`` (the folder is made if missing). The file is 0644, not ``mkstemp``'s 0600: a committed or
    shared file stays readable by the machine's other users."""
    path = Path(path)
    tmp = _temporary(path, data)
    try:
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


@contextlib.contextmanager
def _folder_lock(folder: Path) -> Iterator[None]:
    """An exclusive ``flock`` on the folder itself (no lock file is left in it): two tools that check and
    replace a file there do it one after the other."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


def write_if_unchanged(path: str | Path, data: bytes, read: bytes | None) -> Path:
    """Replace ``path`` with ``data`` only if it still holds ``read`` (what the tool read before its work;
    None: it did not exist), through a temporary file of its own; otherwise :class:`ChangedSinceRead` and
    ``path`` is left as it is, so that an edit made meanwhile (a line added while a tool generated for a
    minute) is never written over."""
    path = Path(path)
    tmp = _temporary(path, data)
    try:
        with _folder_lock(path.parent):
            try:
                now: bytes | None = path.read_bytes()
            except FileNotFoundError:
                now = None
            if now != read:
                raise ChangedSinceRead(
                    f"{path} changed since it was read: nothing written (the change is kept); run again"
                )
            os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
