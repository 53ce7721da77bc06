"""The window tool (a pilot's figures from records) and the lab's ``--set FIELD=VALUE``."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from mcrs_lab.analysis import window
from mcrs_lab.analysis.env_fields import scenario_with

RECORDS = Path(__file__).resolve().parents[1] / "results" / "records" / "baselines" / "campaign"
SEEDS = [RECORDS / f"map10_qmix_seed{k}.json" for k in range(3)]


def test_window_means_and_values_at_steps_match_the_records_own_points(capsys):
    record = json.loads(SEEDS[0].read_text())
    points = record["scalars"]["eval/no_fly_violations"]
    inside = [v for step, v in points if 11000 <= step <= 80000]
    at = [v for step, v in points if step <= 200000][-1]
    assert window.main([str(SEEDS[0]), "--from", "11000", "--to", "80000", "--at", "200000",
                        "--metric", "no_fly_violations"]) == 0  # fmt: skip
    row = next(line for line in capsys.readouterr().out.splitlines() if "map10 qmix" in line)
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1] == "0"
    assert float(cells[2]) == pytest.approx(sum(inside) / len(inside), abs=5e-3)
    assert float(cells[3]) == pytest.approx(at, abs=5e-3)


def test_a_step_beyond_the_run_is_blank_and_seeds_are_rows(capsys):
    assert window.main([*map(str, SEEDS), "--at", "5000000", "--metric", "episode_reward"]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if "map10 qmix" in line]
    assert len(rows) == 3
    assert [row.strip().strip("|").split("|")[-1].strip() for row in rows] == ["", "", ""]


def test_window_refuses_bad_arguments_in_one_line(tmp_path):
    with pytest.raises(SystemExit, match="need 0 <= from <= to"):
        window.main([str(SEEDS[0]), "--from", "10", "--to", "5"])
    with pytest.raises(SystemExit, match="no training run or record under"):
        window.main([str(tmp_path)])
    bad = tmp_path / "bad.json"
    shutil.copy(SEEDS[0], bad)
    record = json.loads(bad.read_text())
    record["scalars"]["eval/episode_reward"] = "nonsense"
    bad.write_text(json.dumps(record))
    with pytest.raises(SystemExit, match="window: error"):
        window.main([str(bad)])


def test_set_reads_fields_as_values_and_names_bad_ones():
    config = scenario_with("tool", "map10", ["p_detect=0.9", "p_false_alarm=0.1", "discovery_rule=target"])
    assert (config.p_detect, config.p_false_alarm, config.discovery_rule) == (0.9, 0.1, "target")
    with pytest.raises(SystemExit, match="tool: error: --set 'p_detect': must be FIELD=VALUE"):
        scenario_with("tool", "map10", ["p_detect"])
    with pytest.raises(SystemExit, match="is not a scalar"):
        scenario_with("tool", "map10", ["p_detect=[1, 2]"])
    with pytest.raises(SystemExit, match=r"discovery_rule='x': must be one of \['belief', 'target'\]"):
        scenario_with("tool", "map10", ["discovery_rule=x"])
    with pytest.raises(SystemExit, match="unknown environment field"):
        scenario_with("tool", "map10", ["p_detekt=0.5"])


def test_reward_under_the_target_rule_takes_out_the_false_discoveries_only_under_eq_24(capsys):
    pilot = RECORDS.parents[1] / "pilot" / "baselines" / "cpu" / "map10_qmix_seed0.json"
    record = json.loads(pilot.read_text())
    assert record["config"]["env"]["discovery_rule"] == "belief"
    reward = dict(map(tuple, record["scalars"]["eval/episode_reward"]))[200000]
    false = dict(map(tuple, record["scalars"]["eval/false_discoveries"]))[200000]
    old = dict(map(tuple, json.loads(SEEDS[0].read_text())["scalars"]["eval/episode_reward"]))[200000]
    assert window.main([str(pilot), str(SEEDS[0]), "--at", "200000", "--metric", "reward_target_r2"]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if "map10 qmix" in line]
    values = {row.split("|")[1].strip(): float(row.split("|")[-2]) for row in rows}
    under_eq_24 = next(v for label, v in values.items() if "discovery_rule=belief" in label)
    under_target = next(v for label, v in values.items() if "discovery_rule=target" in label)
    assert under_eq_24 == pytest.approx(reward - false, abs=5e-3) and false > 0
    assert under_target == pytest.approx(old, abs=5e-3)
