"""How long the campaign's points will take (mcrs_lab.campaign.pace): which recorded runs set a point's pace,
and the time left that ``mcrs-campaign status`` and ``run --dry-run`` print."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from mcrs_lab.analysis.records import write_record
from mcrs_lab.analysis.runs import RECORD_FORMAT, RECORD_VERSION, read_record
from mcrs_lab.campaign.cli import main as campaign_main
from mcrs_lab.campaign.matrix import load_matrix
from mcrs_lab.campaign.pace import TWO_THREAD_SPEEDUP, MachinePace, Pace, left_line, thread_speedup
from tests.test_campaign import TWO_POINTS

#: test_campaign's two map10 points, and one on map15.
THREE_POINTS = (
    TWO_POINTS
    + """  figb:
    experiment: comm_range
    env: [map15]
    algo: [qmix]
"""
)


def _training(env: str, algo: str, steps: int, hours: float, status: str = "finished") -> dict:
    """A training record of ``steps`` env steps over ``hours`` of sessions."""
    return {
        "format": RECORD_FORMAT,
        "version": RECORD_VERSION,
        "kind": "training",
        "run_dir": f"outputs/{env}_{algo}",
        "status": status,
        "total_env_steps": 200,
        "checkpoint_env_steps": steps,
        "sessions": [{"wall_s": hours * 1800.0}, {"wall_s": hours * 1800.0}],
        "final_eval": {},
        "config": {"env": {"name": env}, "algo": {"name": algo}, "seed": 0},
        "scalars": {},
    }


def test_a_points_pace_is_its_algorithms_own_runs_then_older_ones_then_the_slowest_on_its_map(
    tmp_path: Path,
) -> None:
    records = tmp_path / "records"
    write_record(records / "baselines" / "campaign" / "q.json", _training("map20", "qmix", 100, 1.0))
    write_record(records / "baselines" / "campaign" / "v.json", _training("map20", "vdn", 300, 1.0))
    write_record(
        records / "baselines" / "campaign" / "v1.json", _training("map20", "vdn", 100, 2.0, "stopped")
    )
    # An older campaign's runs, a level deeper: they answer only where the campaign's own have nothing.
    write_record(records / "near" / "baselines" / "campaign" / "q.json", _training("map20", "qmix", 900, 1.0))
    write_record(records / "near" / "baselines" / "campaign" / "e.json", _training("map20", "emc", 50, 1.0))
    write_record(
        records / "near" / "lambda" / "campaign" / "c.json", _training("map10", "cnn_semu", 360, 0.5)
    )
    (records / "near" / "shield").mkdir(parents=True)
    (records / "near" / "shield" / "broken.json").write_text(f'{{"format": "{RECORD_FORMAT}", "version": 1')
    pace = Pace.read(records)  # a broken file below gives no pace and stops nothing
    assert pace.speed("map20", "qmix") == pytest.approx(100 / 3600)  # its own run, not the older 900
    assert pace.speed("map20", "vdn") == pytest.approx((300 / 3600 + 100 / 7200) / 2)  # stopped runs count
    assert pace.speed("map20", "emc") == pytest.approx(50 / 3600)  # an older run of that algorithm
    assert pace.speed("map20", "emu") == pytest.approx(100 / 3600)  # the slowest of the campaign's own
    assert pace.speed("map10", "qmix") == pytest.approx(720 / 3600)  # the slowest older run on map10
    assert pace.speed("map15", "qmix") is None
    # The campaign whose folder holds this one (the lured campaign beside results/records/paper) answers
    # last, from its own <experiment>/<budget> folders only.
    write_record(tmp_path / "baselines" / "campaign" / "q15.json", _training("map15", "qmix", 540, 1.0))
    write_record(tmp_path / "baselines" / "campaign" / "q20.json", _training("map20", "qmix", 9000, 1.0))
    write_record(tmp_path / "a" / "b" / "c" / "deep.json", _training("map30", "qmix", 100, 1.0))
    pace = Pace.read(records)
    assert pace.speed("map15", "qmix") == pytest.approx(540 / 3600)
    assert pace.speed("map15", "vdn") == pytest.approx(540 / 3600)  # the slowest on map15
    assert pace.speed("map20", "qmix") == pytest.approx(100 / 3600)  # its own run still first
    assert pace.speed("map30", "qmix") is None  # nothing deeper than the outer campaign's folders


def test_left_line_sums_the_known_estimates_and_counts_the_unknown() -> None:
    assert left_line([3600.0, 7200.0, None], 2) == (
        "left: about 3.0 h of runs at the recorded runs' pace (1.5 h at 2 at a time); "
        "1 runs have no estimate (no timed run on their map)"
    )
    assert left_line([], 1) == "left: about 0.0 h of runs at the recorded runs' pace (0.0 h at 1 at a time)"


def test_status_and_the_dry_run_print_the_time_left(tmp_path: Path, capsys) -> None:
    matrix = tmp_path / "m.yaml"
    matrix.write_text(THREE_POINTS)
    records = tmp_path / "records"
    write_record(records / "comm_range" / "smoke" / "earlier.json", _training("map10", "qmix", 100, 1.0))
    args = ["--matrix", str(matrix), "--outputs", str(tmp_path / "outputs"), "--records", str(records)]
    assert campaign_main(["status", *args]) == 0
    # two map10 points of 200 env steps at 100 an hour; the map15 point has no run on its map to go by
    left = (
        "left: about 4.0 h of runs at the recorded runs' pace (2.0 h at 2 at a time); "
        "1 runs have no estimate (no timed run on their map)"
    )
    assert capsys.readouterr().out.rstrip().endswith(left)
    assert campaign_main(["status", *args, "--only", "map10", "--jobs", "1"]) == 0
    assert (
        capsys.readouterr()
        .out.rstrip()
        .endswith("left: about 4.0 h of runs at the recorded runs' pace (4.0 h at 1 at a time)")
    )
    assert campaign_main(["run", *args, "--hours", "10", "--dry-run"]) == 0
    assert left in capsys.readouterr().out.splitlines()
    with pytest.raises(SystemExit, match="--jobs=0: must be >= 1"):
        campaign_main(["status", *args, "--jobs", "0"])


def test_a_pace_is_per_thread_and_a_two_thread_run_is_counted_faster(tmp_path: Path, capsys) -> None:
    """Records of 2-thread runs are brought down to one thread, and --threads 2 estimates are shorter by
    the measured speed-up; without it `run --jobs 1 --threads 2` would refuse a run that fits."""
    records = tmp_path / "records"
    one = _training("map10", "qmix", 100, 1.0)
    two = _training("map10", "vdn", 147, 1.0)
    two["config"]["threads"] = 2
    write_record(records / "comm_range" / "smoke" / "one.json", one)
    write_record(records / "comm_range" / "smoke" / "two.json", two)
    pace = Pace.read(records)
    assert pace.speed("map10", "vdn") == pytest.approx(100 / 3600)  # 147 an hour at 2 threads = 100 at 1
    assert pace.speed("map10", "qmix", threads=2) == pytest.approx(TWO_THREAD_SPEEDUP * 100 / 3600)
    assert thread_speedup(4) == thread_speedup(2) == TWO_THREAD_SPEEDUP and thread_speedup(1) == 1.0
    matrix = tmp_path / "m.yaml"
    matrix.write_text(
        TWO_POINTS.replace("[0, 2]", "[0]")
    )  # one map10 qmix point of 200 env steps: 2 h at 1 thread
    args = ["--matrix", str(matrix), "--outputs", str(tmp_path / "o"), "--records", str(records), "--dry-run"]
    assert campaign_main(["run", *args, "--hours", "1.5", "--jobs", "1"]) == 0
    assert "not started" in capsys.readouterr().out
    assert campaign_main(["run", *args, "--hours", "1.5", "--jobs", "1", "--threads", "2"]) == 0
    assert f"estimated {2 / TWO_THREAD_SPEEDUP:.2f} h" in capsys.readouterr().out


def test_a_machine_slower_than_the_recorded_pace_scales_the_next_estimates() -> None:
    here = MachinePace()
    qplex, cnn, emc = ("map10", "qplex"), ("map10", "cnn_semu"), ("map20", "emc")
    assert here.factor() == 1.0 and here.scale(100.0, emc) == 100.0 and here.scale(None) is None
    here.observe(qplex, 100.0, 250.0)  # a run estimated at 100 s took 250 s here
    here.observe(qplex, 100.0, 150.0)
    here.observe(cnn, 100.0, 110.0)
    # a start of a kind that finished here is scaled by its own kind's ratio, another by the mean of all
    assert here.scale(60.0, qplex) == pytest.approx(120.0)
    assert here.scale(60.0, cnn) == pytest.approx(66.0)
    assert here.factor(emc) == here.factor() == pytest.approx((2.5 + 1.5 + 1.1) / 3)
    faster = MachinePace()
    faster.observe(emc, 100.0, 40.0)  # a faster machine keeps the recorded estimates
    faster.observe(emc, None, 40.0)  # a run without an estimate says nothing
    assert faster.factor(emc) == faster.factor() == 1.0 and faster.ratios == {emc: [0.4]}


def test_finish_only_judges_a_start_by_what_this_machines_runs_took(tmp_path: Path, capsys) -> None:
    """The recorded pace says qmix takes 2 s and vdn 400 s, so 1,080 s hold both; the qmix run takes
    longer here (a process start alone is seconds), and vdn's estimate, scaled as much, no longer fits."""
    matrix = tmp_path / "m.yaml"
    matrix.write_text(TWO_POINTS.replace("algo: [qmix]", "algo: [qmix, vdn]").replace("[0, 2]", "[0]"))
    qmix, vdn = load_matrix(matrix)[0]
    records = tmp_path / "records"
    for algo, hours in (("qmix", 1 / 3600), ("vdn", 200 / 3600)):  # 100 env steps in 1 s and in 200 s
        write_record(
            records / "comm_range" / "smoke" / f"earlier_{algo}.json", _training("map10", algo, 100, hours)
        )
    args = ["--matrix", str(matrix), "--outputs", str(tmp_path / "o"), "--records", str(records)]
    args += ["--hours", "0.3", "--jobs", "1", "--fill", "--finish-only"]
    assert campaign_main(["run", *args, "--dry-run"]) == 0
    plan = capsys.readouterr().out  # at the recorded pace both would run
    assert f"start {qmix.id} (at 0 env steps, estimated 0.00 h)" in plan and f"start {vdn.id} " in plan
    assert campaign_main(["run", *args]) == 0
    out = capsys.readouterr().out
    # the ratio is kept per (map, algorithm): the finished qmix run's own, beside the mean of all
    assert re.search(r"campaign: runs here take \d+\.\d\dx the recorded pace, map10 qmix \d+\.\d\dx", out), (
        out
    )
    assert re.search(
        rf"not started: {vdn.id} needs about \d+\.\d\d h, 0\.\d\d h left \(--finish-only\)", out
    ), out
    assert read_record(qmix.record_path(records))["status"] == "finished"
    assert not vdn.run_dir(tmp_path / "o").exists()
