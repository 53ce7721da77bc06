"""Helpers shared by the benchmark commands."""

from __future__ import annotations

import os


def load_average() -> str:
    """The 1-minute load average: other processes on the machine skew every figure, so show it."""
    try:
        return f"{os.getloadavg()[0]:.2f}"
    except OSError:
        return "n/a"


def pass_fail(ok: bool) -> str:
    return "PASS" if ok else "FAIL"
