"""A file written whole or not at all: a reader sees the old file or the new one, and a failed write leaves no
temporary behind."""

from __future__ import annotations

import contextlib
import fcntl
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

__all__ = ["ChangedSinceRead", "write_bytes_atomic", "write_if_unchanged", "write_text_atomic"]


class ChangedSinceRead(Exception):
    """A file a tool meant to rewrite was changed since it read it, so nothing is written."""


def write_text_atomic(path: str | Path, text: str) -> Path:
    """:func:`write_bytes_atomic` for text (UTF-8)."""
    return write_bytes_atomic(path, text.encode())


def _temporary(path: Path, data: bytes) -> str:
    """Write ``data`` to a new synced 0644 temporary file of its own beside ``path`` and return its name."""
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
    """Write ``data`` to ``path`` through a synced temporary file renamed over it. The file is 0644, not
    ``mkstemp``'s 0600, so a shared file stays readable."""
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
    """An exclusive ``flock`` on the folder itself, leaving no lock file, so that tools replacing a file there
    take turns."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


def write_if_unchanged(path: str | Path, data: bytes, read: bytes | None) -> Path:
    """Replace ``path`` with ``data`` only if it still holds ``read`` (None: it did not exist), else raise
    :class:`ChangedSinceRead`, so an edit made meanwhile is never written over."""
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
