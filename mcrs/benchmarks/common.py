"""Helpers shared by the benchmark commands."""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from contextlib import contextmanager

import torch


def load_average() -> str:
    """The 1-minute load average: other processes on the machine skew every figure, so show it."""
    try:
        return f"{os.getloadavg()[0]:.2f}"
    except OSError:
        return "n/a"


def pass_fail(ok: bool) -> str:
    return "PASS" if ok else "FAIL"


@contextmanager
def benchmark_process(threads: int) -> Iterator[None]:
    """Run a benchmark with ``threads`` torch threads (0: torch's default) and without TorchRL's INFO lines
    (storage allocations would break the tables); restore both after, since tests call ``main`` in-process."""
    previous_threads = torch.get_num_threads()
    torchrl_log = logging.getLogger("torchrl")
    previous_level = torchrl_log.level
    torchrl_log.setLevel(logging.WARNING)
    if threads:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous_threads)
        torchrl_log.setLevel(previous_level)
