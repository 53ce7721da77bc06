"""The paper's table 4 beside ours: the episode reward of the memory methods per delta (the
state-embedding difference threshold) at fractions of training, with the paper's own numbers in the
columns next to ours where the map is the paper's (20 x 20).

The paper reports 0.67M, 1.33M and 2M timesteps; a 1M-step budget shares its 0.67M, and our last step
stands beside its 1.33M and 2M, so a reader sees at once where our runs are against the paper's."""

from __future__ import annotations

import math
from dataclasses import dataclass

from mcrs.experiment.util.tables import markdown, mean_std
from mcrs_lab.analysis.step_notation import seeds_reached, step_labels

#: The map of the paper's hyperparameter study (section 6.3: "using a 20 x 20 map as an example").
PAPER_TABLE4_ENV = "map20"
#: The paper's timesteps (table 4's heading: 0.67, 1.33 and 2.00 M: thirds of its 2M).
PAPER_TABLE4_STEPS = (666_667, 1_333_333, 2_000_000)
#: Table 4 of the paper, (delta, algorithm) -> episode reward at PAPER_TABLE4_STEPS.
PAPER_TABLE4 = {
    (1.3e-4, "emc"): (355.69, 360.20, 367.30),
    (1.3e-4, "semu"): (363.22, 365.63, 370.01),
    (1.3e-4, "cnn_semu"): (359.17, 369.16, 372.11),
    (1.3e-3, "emc"): (356.03, 365.62, 369.75),
    (1.3e-3, "semu"): (358.62, 360.33, 368.35),
    (1.3e-3, "cnn_semu"): (361.91, 363.02, 372.34),
    (1.3e-2, "emc"): (359.43, 361.68, 366.49),
    (1.3e-2, "semu"): (358.84, 361.30, 369.74),
    (1.3e-2, "cnn_semu"): (359.77, 368.24, 371.91),
    (1.3e-1, "emc"): (339.95, 321.97, 311.41),
    (1.3e-1, "semu"): (343.10, 342.96, 349.96),
    (1.3e-1, "cnn_semu"): (337.03, 358.17, 362.51),
}
#: Row order within one delta: the paper's columns (random projection, FC encoder, CNN encoder).
MEMORY_ORDER = ("emc", "semu", "cnn_semu")


@dataclass(frozen=True)
class Table4Row:
    """Our runs of one (delta, algorithm): mean and std over seeds at each of our milestone steps, and
    the last env step its seeds share (a run stopped at a session's end is short of the later columns)."""

    delta: float
    algorithm: str
    seeds: int
    values: list[tuple[float, float]]
    last_step: int


def same_delta(a: float, b: float) -> bool:
    """Whether two deltas are one value (0.0013 from a config, 1.3e-3 from the paper)."""
    return math.isclose(a, b, rel_tol=1e-6)


def paper_rewards(delta: float, algorithm: str) -> tuple[float, ...] | None:
    """The paper's table-4 rewards of (delta, algorithm), or None where the paper has none."""
    for (paper_delta, paper_algo), rewards in PAPER_TABLE4.items():
        if paper_algo == algorithm and same_delta(paper_delta, delta):
            return rewards
    return None


def _order(delta: float, algorithm: str) -> tuple[float, int, str]:
    rank = MEMORY_ORDER.index(algorithm) if algorithm in MEMORY_ORDER else len(MEMORY_ORDER)
    return (delta, rank, algorithm)


def table4(ours: list[Table4Row], steps: list[int], env_name: str) -> tuple[list[dict[str, object]], str]:
    """table4.csv's rows and table4.md: ours at ``steps``; on the paper's map also the paper's columns
    (``0.67M (paper)``, after ours at the nearest step) and the paper's rows we did not run."""
    with_paper = env_name == PAPER_TABLE4_ENV
    rows = list(ours)
    if with_paper:
        rows += [
            Table4Row(delta, algo, 0, [(math.nan, math.nan)] * len(steps), last_step=0)
            for delta, algo in PAPER_TABLE4
            if not any(r.algorithm == algo and same_delta(r.delta, delta) for r in ours)
        ]
    # columns: ours and (on the paper's map) the paper's, by step; ours first where they meet
    columns = [(s, False, k) for k, s in enumerate(steps)]
    if with_paper:
        columns += [(s, True, k) for k, s in enumerate(PAPER_TABLE4_STEPS)]
    # steps equal to two significant figures are one step (the paper's 0.67M is our 668.8k), ours first
    columns.sort(key=lambda c: (float(f"{c[0]:.2g}"), c[1]))
    ours_labels = step_labels(steps)
    header = ["delta", "algorithm", "seeds"] + [
        f"{s / 1e6:.2f}M (paper)" if paper else ours_labels[k] for s, paper, k in columns
    ]
    csv_rows, md_rows = [], []
    for row in sorted(rows, key=lambda r: _order(r.delta, r.algorithm)):
        paper = paper_rewards(row.delta, row.algorithm) if with_paper else None
        csv_row: dict[str, object] = {"delta": row.delta, "algorithm": row.algorithm, "seeds": row.seeds}
        seeds = seeds_reached(row.seeds, row.last_step, row.values) if row.seeds else "-"
        cells = [f"{row.delta:g}", row.algorithm, seeds]
        for step, is_paper, k in columns:
            if is_paper:
                value = paper[k] if paper else math.nan
                csv_row[f"paper_{step}"] = value
                cells.append(f"{value:.2f}" if paper else "-")
            else:
                mean, std = row.values[k]
                csv_row[f"reward_{step}"] = mean
                cells.append(mean_std(mean, std, n=row.seeds, missing="-"))
        csv_rows.append(csv_row)
        md_rows.append(cells)
    return csv_rows, markdown(header, md_rows, left=2)
