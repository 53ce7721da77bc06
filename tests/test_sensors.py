"""The table of the heuristics and the reward bound by sensor model (mcrs-report's sensors.md)."""

from __future__ import annotations

from pathlib import Path

import pytest

from mcrs.env.config import scenario
from mcrs_lab.analysis.bound import reward_bound
from mcrs_lab.analysis.runs import EvaluationRow
from mcrs_lab.analysis.sensors import sensor_of, sensor_table


def row(policy: str, seed: int, reward: float, **env) -> EvaluationRow:
    config = scenario("map10", **env).scenario()
    means = {"episode_reward": reward, "targets_found": 3.0, "false_discoveries": 1.0 + seed}
    return EvaluationRow(Path(f"/e/{policy}{seed}"), policy, "map10", 5.0, seed, 4, means, env=config)


def test_one_sensor_makes_no_table_and_unknown_configs_are_left_out():
    rows = [row("greedy", k, 80.0 + k) for k in range(2)]
    assert sensor_table(rows, "map10") is None
    bare = EvaluationRow(Path("/e/x"), "greedy", "map10", 5.0, 0, 4, {"episode_reward": 1.0})
    assert sensor_of(bare) is None


def test_rows_group_by_sensor_with_seed_statistics_and_the_bounds_of_the_same_layouts():
    rows = [row("coverage", k, 90.0 + k) for k in range(3)]
    rows += [row("coverage", k, 95.0 + 2 * k, p_detect=1.0, p_false_alarm=0.0) for k in range(2)]
    table = sensor_table(rows, "map10")
    lines = table.splitlines()
    coverage = [line for line in lines if " coverage |" in line]
    cells = [[c.strip() for c in line.strip("|").split("|")] for line in coverage]
    assert cells[0][:4] == ["0.8 / 0.2", "coverage", "3", "91.00 ± 1.00"]
    assert cells[1][:4] == ["1 / 0", "coverage", "2", "96.00 ± 1.41"]
    config = scenario("map10")
    strict = sum(float(reward_bound(config, 4, s).mean()) for s in range(3)) / 3
    exact = (
        sum(
            float(reward_bound(config.replace(p_detect=1.0, p_false_alarm=0.0), 4, s).mean())
            for s in range(3)
        )
        / 3
    )
    favour = next(line for line in lines if "0.8 / 0.2" in line and "team's favour" in line)
    never = next(line for line in lines if "0.8 / 0.2" in line and "never errs" in line)
    assert f"{strict:.2f}" in favour and f"{exact:.2f}" in never
    assert strict > exact  # eq. 24 with a sensor that errs: every cell may be a discovery


def test_rows_of_another_map_are_not_in_the_table():
    rows = [row("coverage", 0, 90.0), row("coverage", 0, 95.0, p_detect=1.0, p_false_alarm=0.0)]
    assert sensor_table(rows, "map20") is None
    assert sensor_of(rows[1]) == pytest.approx((1.0, 0.0))
