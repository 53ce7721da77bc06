"""Tables as markdown (for docs and the terminal) and CSV (for anything else)."""

from __future__ import annotations

import csv
import math
from pathlib import Path


def mean_std(mean: float, std: float, digits: int = 2, n: int | None = None, missing: str = "n/a") -> str:
    """``mean ± std``, or the mean alone when ``n`` is 1, since one sample has no spread; ``missing`` for
    no value (a metric not logged, or a step a run has not reached)."""
    if math.isnan(mean):
        return missing
    if n is not None and n < 2:
        return f"{mean:.{digits}f}"
    return f"{mean:.{digits}f} ± {std:.{digits}f}"


def markdown(header: list[str], rows: list[list[str]], left: int = 1) -> str:
    """A markdown table aligned as text: the first ``left`` columns left, the others right."""
    widths = [max(len(str(row[k])) for row in [header, *rows]) for k in range(len(header))]

    def line(cells: list[str]) -> str:
        padded = [
            str(c).ljust(w) if k < left else str(c).rjust(w)
            for k, (c, w) in enumerate(zip(cells, widths, strict=True))
        ]
        return "| " + " | ".join(padded) + " |"

    rule = "|" + "|".join("-" * (w + 1) + (":" if k >= left else "-") for k, w in enumerate(widths)) + "|"
    return "\n".join([line(header), rule, *(line(row) for row in rows)])


def write_csv(path: Path, rows: list[dict[str, object]]) -> Path:
    """One row per dict; the columns are the keys in first-seen order."""
    columns: list[str] = []
    for row in rows:
        columns += [k for k in row if k not in columns]
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
    return path
