"""Env-step counts as people write them: ``100k``, ``1.33M`` in table headings, and read back from a
command line (``--milestones 100k,300k,1M``)."""

from __future__ import annotations

import math

#: Suffixes an env-step count may carry.
STEP_SUFFIXES = {"": 1, "k": 1_000, "M": 1_000_000}


def format_steps(steps: int, extra: int = 0) -> str:
    """``11.2k``, ``1.00M``: one decimal in thousands, two in millions, plus ``extra``; under a thousand,
    the number (``0``)."""
    if steps < 1_000:
        return str(steps)
    if steps >= 1_000_000:
        return f"{steps / 1e6:.{2 + extra}f}M"
    return f"{steps / 1e3:.{1 + extra}f}k"


def seeds_reached(seeds: int, last_step: int, values: list[tuple[float, float]]) -> str:
    """A table's seed count, and where their ``values`` (mean, std per column) stop short of a column (a
    run stopped at a session's end, to resume) how far they got: ``1 (to 169.6k)``, so the dashes past it
    read as "not reached yet"."""
    short = any(math.isnan(mean) for mean, _ in values)
    return f"{seeds} (to {format_steps(last_step)})" if short else str(seeds)


def step_labels(steps: list[int]) -> list[str]:
    """Column headings for env steps (``11.2k``, ``1.33M``), with as many decimals as it takes for
    distinct steps to get distinct headings (11,150 and 11,200 are both ``11.2k`` at one decimal)."""
    for extra in range(4):
        labels = [format_steps(s, extra) for s in steps]
        if len(set(labels)) == len(set(steps)):
            return labels
    return [f"{s:,}" for s in steps]


def parse_step_list(text: str) -> list[int]:
    """``"100k,300k,1M"`` -> ``[100000, 300000, 1000000]`` (sorted, each once); a ValueError names the
    item that is not a positive whole number of steps."""
    steps = []
    for item in text.split(","):
        item = item.strip()
        number, suffix = (item[:-1], item[-1]) if item[-1:] in ("k", "M") else (item, "")
        try:
            value = float(number) * STEP_SUFFIXES[suffix]
        except ValueError:
            value = float("nan")
        if not (value > 0 and value == int(value)):
            raise ValueError(
                f"{item!r} is not an env step count: positive whole steps, comma-separated, such as "
                "100k,300k,1M or 150000"
            )
        steps.append(int(value))
    return sorted(set(steps))
