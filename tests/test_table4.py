"""The paper's table 4 beside ours (mcrs_lab.analysis.table4): its numbers, columns and rows."""

from __future__ import annotations

import math

from mcrs_lab.analysis.table4 import PAPER_TABLE4, Table4Row, paper_rewards, table4


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


STEPS = [332_800, 668_800, 1_001_600]  # a 1M run's evaluations nearest its thirds


def test_the_paper_columns_stand_beside_ours_at_the_steps_we_share() -> None:
    ours = [
        Table4Row(0.0013, "cnn_semu", 3, [(330.0, 1.0), (340.0, 2.0), (345.0, 3.0)], last_step=1_001_600),
        Table4Row(0.0013, "emc", 2, [(320.0, 1.0), (325.0, 2.0), (326.0, 3.0)], last_step=1_001_600),
        Table4Row(0.13, "emc", 1, [(300.0, 0.0), (310.0, 0.0), (math.nan, math.nan)], last_step=672_000),
        Table4Row(0.013, "emc", 1, [(math.nan, math.nan)] * 3, last_step=169_600),
    ]
    rows, md = table4(ours, STEPS, "map20")
    header = _cells(md.splitlines()[0])
    ours_then_paper = ["332.8k", "668.8k", "0.67M (paper)", "1.00M", "1.33M (paper)", "2.00M (paper)"]
    assert header == ["delta", "algorithm", "seeds", *ours_then_paper]
    # every (delta, algorithm) of the paper's table: ours where we ran it, a dash where we did not
    assert len(rows) == len(PAPER_TABLE4)
    assert [(r["delta"], r["algorithm"]) for r in rows[3:6]] == [
        (0.0013, "emc"),
        (1.3e-3, "semu"),
        (0.0013, "cnn_semu"),
    ]
    emc = rows[3]
    assert (emc["seeds"], emc["reward_668800"], emc["paper_666667"], emc["paper_2000000"]) == (
        2,
        325.0,
        356.03,
        369.75,
    )
    cells = {tuple(row[:2]): row[2:] for row in map(_cells, md.splitlines()[2:])}
    emc_row = ["320.00 ± 1.00", "325.00 ± 2.00", "356.03", "326.00 ± 3.00", "365.62", "369.75"]
    assert cells["0.0013", "emc"] == ["2", *emc_row]
    # one seed: no spread; a run stopped short of a column says how far it got, the column a dash
    assert cells["0.13", "emc"][:5] == ["1 (to 672.0k)", "300.00", "310.00", "339.95", "-"]
    assert cells["0.013", "emc"] == ["1 (to 169.6k)", "-", "-", "359.43", "-", "361.68", "366.49"]
    assert cells["0.00013", "semu"] == ["-", "-", "-", "363.22", "-", "365.63", "370.01"]  # not run by us


def test_off_the_papers_map_the_table_is_ours_alone() -> None:
    ours = [Table4Row(0.13, "cnn_semu", 2, [(1.0, 0.5), (2.0, 0.5), (3.0, 0.5)], last_step=1_001_600)]
    rows, md = table4(ours, STEPS, "map10")
    assert rows == [
        {
            "delta": 0.13,
            "algorithm": "cnn_semu",
            "seeds": 2,
            **{f"reward_{s}": float(k + 1) for k, s in enumerate(STEPS)},
        }
    ]
    assert "paper" not in md


def test_paper_rewards_match_deltas_as_configs_write_them() -> None:
    assert paper_rewards(0.0013, "cnn_semu") == (361.91, 363.02, 372.34)
    assert paper_rewards(0.13, "emc") == (339.95, 321.97, 311.41)
    assert paper_rewards(0.0013, "emu") is None and paper_rewards(0.5, "emc") is None
