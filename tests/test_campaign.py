"""mcrs-campaign: the section-6 matrix, status from the disk, and real smoke runs resumed, recorded and
stopped by a signal."""

from __future__ import annotations

import fcntl
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mcrs.experiment.run import checkpoint as ckpt
from mcrs_lab.analysis.records import write_record
from mcrs_lab.analysis.runs import RECORD_FORMAT, RECORD_VERSION, read_record
from mcrs_lab.campaign import runner
from mcrs_lab.campaign.cli import heuristic_folders
from mcrs_lab.campaign.cli import main as campaign_main
from mcrs_lab.campaign.evaluations import load_evaluations
from mcrs_lab.campaign.matrix import DEFAULT_MATRIX, MatrixError, campaign_roots, load_matrix, select
from tests.test_report import read_csv
from tests.train_helpers import compose_config

pytestmark = pytest.mark.slow

CAMPAIGNS = Path(__file__).resolve().parents[1] / "mcrs_lab" / "campaign"
NEAR_MATRIX = CAMPAIGNS / "section6_near.yaml"
LURED_MATRIX = CAMPAIGNS / "section6.yaml"
OLD_TASK = ("env.safety_rule=near", "algo.time_limit=bootstrap")

TWO_POINTS = """
budget: smoke
seeds: [0]
figures:
  figa:
    experiment: comm_range
    env: [map10]
    algo: [qmix]
    sweep: {env.comm_range: [0, 2]}
"""


#: The fields every training record has (mcrs_lab.analysis.record_schema refuses a record without them).
RECORD_FIELDS = {
    "total_env_steps": 200,
    "checkpoint_env_steps": 200,
    "final_eval": {},
    "config": {"env": {"name": "map10"}, "algo": {"name": "qmix"}, "seed": 0},
    "scalars": {},
}


def test_section6_matrix_on_the_papers_task_and_its_shared_points() -> None:
    """The landed campaign: the paper's penalty and horizon (the defaults), and the no-fly and r2 reading it
    ran under, which the defaults no longer are (docs/ENVIRONMENT.md, "No-fly cells and the discovery
    reward"): every point says so in its overrides."""
    points, titles = load_matrix(LURED_MATRIX)
    assert list(titles) == ["fig7", "table4", "fig6", "fig8"]
    assert len(points) == 21 + 9 + 18 + 6 and len({p.id for p in points}) == len(points)
    assert all(p.budget == "campaign" for p in points)
    lured = ("env.no_fly_view=belief", "env.no_fly_prior=unknown", "env.discovery_rule=target")
    assert all(p.overrides == lured for p in points)  # and safety_rule=enter, time_limit=terminal: defaults
    fig7 = select(points, ["fig7"])
    assert sorted({p.algo for p in fig7}) == sorted(
        ["qmix", "vdn", "qplex", "emc", "emu", "semu", "cnn_semu"]
    )
    assert {p.env for p in fig7} == {"map20"} and {p.seed for p in fig7} == {0, 1, 2}
    table4 = select(points, ["table4"])
    deltas = {(p.algo, dict(p.settings).get("algo.memory.delta")) for p in table4}
    assert deltas == {(a, d) for a in ("emc", "semu", "cnn_semu") for d in (None, 0.13)}
    fig6 = select(points, ["fig6", "seed0"])
    assert [p.id for p in fig6] == [
        f"baselines/{m}_{a}_seed0" for m in ("map10", "map15") for a in ("qmix", "qplex", "cnn_semu")
    ]
    fig8 = select(points, ["fig8", "seed0"])
    assert sorted(p.algo for p in fig8) == ["cnn_semu", "emu", "emu_370", "emu_change", "qmix"]
    cfg = compose_config("algo=emu", "env=map20", tiny=False)
    assert cfg.algo.incentive_threshold == 365.0 and cfg.env.safety_rule == "enter"
    assert str(cfg.algo.time_limit) == "terminal"


def test_a_campaign_files_name_chooses_its_roots_and_the_default_file_is_the_papers(
    tmp_path: Path, capsys, monkeypatch
) -> None:
    """Without --records and --outputs a file named ``probe`` trains in outputs/probe/ and records in
    results/records/probe/; a file without a name keeps results/records/ and outputs/campaign/; the
    flags win over both."""
    assert campaign_roots(DEFAULT_MATRIX) == (Path("results/records/paper"), Path("outputs/paper"))
    assert load_matrix()[1].keys() == load_matrix(CAMPAIGNS / "section6_paper.yaml")[1].keys()
    assert campaign_roots(LURED_MATRIX) == (Path("results/records"), Path("outputs/campaign"))
    monkeypatch.chdir(tmp_path)
    Path("m.yaml").write_text("name: probe\n" + TWO_POINTS)
    assert campaign_main(["run", "--matrix", "m.yaml", "--hours", "1", "--dry-run"]) == 0
    dirs = [w.split("=", 1)[1] for w in capsys.readouterr().out.split() if w.startswith("hydra.run.dir=")]
    assert dirs == [f"outputs/probe/comm_range/smoke/map10_qmix_rc{r}_seed0" for r in (0, 2)]
    record = Path("results/records/probe/comm_range/smoke/map10_qmix_rc0_seed0.json")
    fields = {"format": RECORD_FORMAT, "version": RECORD_VERSION, "kind": "training", "run_dir": "x"}
    write_record(record, {**fields, **RECORD_FIELDS, "status": "finished"})
    campaign_main(["status", "--matrix", "m.yaml"])
    assert "1 done" in capsys.readouterr().out
    campaign_main(["status", "--matrix", "m.yaml", "--records", "elsewhere", "--outputs", "other"])
    assert "0 done" in capsys.readouterr().out
    Path("m.yaml").write_text(TWO_POINTS)
    campaign_main(["run", "--matrix", "m.yaml", "--hours", "1", "--dry-run"])
    assert "hydra.run.dir=outputs/campaign/comm_range/smoke/" in capsys.readouterr().out


def test_a_campaigns_report_holds_its_heuristics_on_the_learners_episodes(tmp_path: Path) -> None:
    """``mcrs-campaign report`` adds the records of the file's heuristics-only evaluations on the map,
    where ``mcrs-campaign evaluate`` put them (the paper's: heuristics/default/eval/<map>), and falls back
    to the older ``<records>/heuristics/<map>`` where there are none."""
    paper = load_evaluations(DEFAULT_MATRIX, set(load_matrix(DEFAULT_MATRIX)[1]))
    committed = CAMPAIGNS.parents[1] / "results" / "records" / "paper"
    assert heuristic_folders(paper, committed, "map20") == [committed / "heuristics/default/eval/map20"]
    records = tmp_path / "records"
    assert heuristic_folders(paper, records, "map20") == []
    (records / "heuristics" / "map20").mkdir(parents=True)
    assert heuristic_folders(paper, records, "map20") == [records / "heuristics" / "map20"]
    (records / "heuristics" / "default" / "eval" / "map20").mkdir(parents=True)
    assert heuristic_folders(paper, records, "map20") == [records / "heuristics/default/eval/map20"]
    assert heuristic_folders(paper, records, "map10") == []


def test_a_figure_may_name_its_own_seeds(tmp_path: Path) -> None:
    beyond = Path(__file__).resolve().parents[1] / "mcrs_lab" / "campaign" / "beyond_paper.yaml"
    points, _ = load_matrix(beyond)
    seeds = {fig: sorted({p.seed for p in select(points, [fig])}) for fig in ("shield", "shields")}
    assert seeds == {"shield": [0], "shields": [0, 1, 2]}  # the file's seeds, and the figure's own
    # a swept discount: in the point's name, the run's config; the figure's name means the figure, not
    # the experiment of the same name (whose points include shields_gamma05's seeds 1 and 2)
    gamma = select(points, ["shields_gamma"])
    assert [p.id for p in gamma] == [f"shields_gamma/map20_qmix_gamma{g}_seed0" for g in ("0.9", "0.5")]
    assert [dict(p.settings) for p in gamma] == [{"algo.gamma": 0.9}, {"algo.gamma": 0.5}]
    # a figure at three seeds of one swept value: its seed 0 is the probe's run, one point in two figures
    three = select(points, ["shields_gamma05"])
    assert [p.id for p in three] == [f"shields_gamma/map20_qmix_gamma0.5_seed{s}" for s in (0, 1, 2)]
    assert three[0] is gamma[1] and three[0].figures == ("shields_gamma", "shields_gamma05")
    assert [p.id for p in select(points, ["shields_gamma025"])] == [
        "shields_gamma/map20_qmix_gamma0.25_seed0"
    ]
    matrix = tmp_path / "m.yaml"
    matrix.write_text(TWO_POINTS.replace("    sweep:", "    seeds: [3, 5]\n    sweep:"))
    assert sorted(p.seed for p in load_matrix(matrix)[0]) == [3, 3, 5, 5]
    matrix.write_text(TWO_POINTS.replace("    sweep:", "    seeds: [-1]\n    sweep:"))
    with pytest.raises(MatrixError, match=r"figure figa: seeds: -1 is not a whole number"):
        load_matrix(matrix)


def test_section6_near_matrix_keeps_the_old_task_for_every_point() -> None:
    points, titles = load_matrix(NEAR_MATRIX)
    assert list(titles) == ["fig7", "table4", "fig5", "fig10", "fig6"]
    assert len(points) == 21 + 9 + 30 + 15 + 9 and len({p.id for p in points}) == len(points)
    assert all(p.budget == "campaign" for p in points)
    fig7 = select(points, ["fig7"])
    assert sorted({p.algo for p in fig7}) == sorted(
        ["qmix", "vdn", "qplex", "emc", "emu", "semu", "cnn_semu"]
    )
    assert {p.env for p in fig7} == {"map20"} and {p.seed for p in fig7} == {0, 1, 2}
    table4 = select(points, ["table4"])
    deltas = {(p.algo, dict(p.settings).get("algo.memory.delta")) for p in table4}
    assert deltas == {(a, d) for a in ("emc", "semu", "cnn_semu") for d in (None, 0.13)}
    fig5 = select(points, ["fig5"])
    assert [dict(p.settings).get("env.comm_range", "fig7") for p in fig5 if p.seed == 0] == [
        "fig7",  # figure 7's QMIX at map20's default R_c
        *range(5),
        *range(6, 11),
    ]
    # the runs shared with figure 7 really are the missing values: the defaults on map20
    for algo in ("emc", "semu", "cnn_semu"):
        assert compose_config(f"algo={algo}", "env=map20", tiny=False).algo.memory.delta == pytest.approx(
            1.3e-3
        )
    assert compose_config("env=map20", tiny=False).env.comm_range == 5.0
    assert {dict(p.settings)["algo.memory_weight"] for p in select(points, ["fig10"])} == {
        0.01,
        0.05,
        0.1,
        0.5,
        1.0,
    }
    assert [p.id for p in select(points, ["fig6", "seed0"])] == [
        "baselines/map15_qmix_seed0",
        "baselines/map15_qplex_seed0",
        "baselines/map15_cnn_semu_seed0",
    ]
    (emu,) = select(points, ["emu", "seed0"])
    assert emu.overrides == (*OLD_TASK, "algo.incentive_threshold=305")
    assert all(p.overrides[:2] == OLD_TASK for p in points)


def test_bad_filters_and_files_are_one_line_errors(tmp_path: Path, capsys) -> None:
    with pytest.raises(SystemExit, match=r"--only=fig9: unknown fig9; allowed: baselines, cnn_semu"):
        campaign_main(["status", "--only", "fig9"])
    with pytest.raises(SystemExit, match=r"--matrix=.*nope.yaml: no such file"):
        campaign_main(["status", "--matrix", str(tmp_path / "nope.yaml")])
    bad = tmp_path / "bad.yaml"
    bad.write_text(TWO_POINTS.replace("env.comm_range", "algo.memory.delta"))
    with pytest.raises(
        SystemExit, match=r"sweep \['algo.memory.delta'\] is not swept by experiment=comm_range"
    ):
        campaign_main(["status", "--matrix", str(bad)])
    with pytest.raises(SystemExit, match="--jobs=0: must be >= 1"):
        campaign_main(["run", "--hours", "1", "--jobs", "0"])
    with pytest.raises(
        MatrixError, match="budget='huge': allowed values are campaign, cpu, paper, quickstart, smoke"
    ):
        bad.write_text(TWO_POINTS.replace("budget: smoke", "budget: huge"))
        load_matrix(bad)


def _fake_run(run_dir: Path, env_steps: int) -> None:
    """A run directory whose last.pt says how far it got (all that status reads)."""
    ckpt.save_atomic({"counters": {"env_steps": env_steps}, "config": {}}, ckpt.checkpoint_path(run_dir))


def test_status_tells_done_unrecorded_partial_and_missing(tmp_path: Path, capsys) -> None:
    matrix = tmp_path / "m.yaml"
    matrix.write_text(TWO_POINTS.replace("[0, 2]", "[0, 1, 2, 3]"))
    points, _ = load_matrix(matrix)
    outputs, records = tmp_path / "out", tmp_path / "rec"
    done, unrecorded, partial, missing = points
    _fake_run(done.run_dir(outputs), 200)
    record = {"format": RECORD_FORMAT, "version": RECORD_VERSION, "kind": "training", "run_dir": "x",
              **RECORD_FIELDS}  # fmt: skip
    write_record(done.record_path(records), {**record, "status": "finished", "checkpoint_env_steps": 200})
    _fake_run(unrecorded.run_dir(outputs), 200)
    _fake_run(partial.run_dir(outputs), 100)
    write_record(missing.record_path(records), {**record, "status": "stopped", "checkpoint_env_steps": 50})
    args = ["--matrix", str(matrix), "--outputs", str(outputs), "--records", str(records)]
    assert campaign_main(["status", *args]) == 0
    out = capsys.readouterr().out
    rows = [[c.strip() for c in line.split("|")[1:-1]] for line in out.splitlines() if "map10_qmix" in line]
    table = {row[0]: row[2:] for row in rows}  # point -> state, env steps, where
    assert table[done.id] == ["done", "200", "record of x"]
    assert table[unrecorded.id] == ["unrecorded", "200", str(unrecorded.run_dir(outputs))]
    assert table[partial.id] == ["partial", "100", str(partial.run_dir(outputs))]
    assert table[missing.id] == [
        "missing",
        "0",
        "a stopped record at 50 steps of x, no checkpoint of it here: starts from 0",
    ]
    assert "4 points (200 env steps each): 1 done, 1 unrecorded, 1 partial, 1 missing" in out
    assert "\ndone by figure: figa 1 of 4\n" in out
    assert campaign_main(["run", *args, "--hours", "1", "--dry-run"]) == 0
    plan = capsys.readouterr().out.splitlines()
    assert plan[0] == f"record {unrecorded.run_dir(outputs)}"
    assert plan[1].startswith(f"resume {partial.id} (at 100 env steps, estimated unknown): ")
    assert f"resume={partial.run_dir(outputs)} train.total_env_steps=200 threads=1" in plan[1]
    assert "train.checkpoint_minutes=10" in plan[1]  # also for runs first launched without the time interval
    assert plan[2].startswith(f"start {missing.id} ")
    assert (
        "experiment=comm_range budget=smoke env=map10 algo=qmix env.comm_range=3 seed=0 threads=1" in plan[2]
    )
    assert f"hydra.run.dir={missing.run_dir(outputs)}" in plan[2]
    # No record here says how long a run took: the time left is unknown.
    assert (
        plan[3]
        == "left: about 0.0 h of runs at the recorded runs' pace (0.0 h at 2 at a time); 2 runs have no estimate (no timed run on their map)"
    )
    assert plan[4] == "2 runs, 2 at a time, no new start after 1 h"
    # --finish-only resumes a partial run whatever its estimate, and starts no run it cannot time
    assert campaign_main(["run", *args, "--hours", "1", "--dry-run", "--fill", "--finish-only"]) == 0
    plan = capsys.readouterr().out.splitlines()
    assert plan[1].startswith(
        f"resume {partial.id} (at 100 env steps, estimated unknown, stopped at the deadline)"
    )
    assert plan[2] == f"not started: {missing.id} has no estimate, 1.00 h left (--finish-only)"


def test_run_resumes_a_partial_point_first_and_records_every_run(tmp_path: Path, capsys) -> None:
    matrix = tmp_path / "m.yaml"
    matrix.write_text(TWO_POINTS)
    missing, partial = load_matrix(matrix)[0]  # the file's order puts the missing one first
    outputs, records = tmp_path / "outputs", tmp_path / "records"
    # the partial point: its own command, stopped at 100 of the budget's 200 env steps
    half = subprocess.run(
        [*partial.train_command(outputs), "train.total_env_steps=100"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert half.returncode == 0, half.stderr[-2000:]
    args = ["--matrix", str(matrix), "--outputs", str(outputs), "--records", str(records)]
    assert campaign_main(["run", *args, "--hours", "1", "--jobs", "1"]) == 0
    out = capsys.readouterr().out
    assert out.index(f"resumed {partial.id}") < out.index(f"started {missing.id}")
    for point in (partial, missing):
        record = read_record(point.record_path(records))
        assert (record["status"], record["checkpoint_env_steps"]) == ("finished", 200)
        (session,) = record["sessions"]
        assert session["returncode"] == 0 and not session["stopped_by_campaign"]
        assert session["machine"]["cpu_count"] >= 1 and len(session["git"]["commit"]) == 40
        assert "replay" not in ckpt.load(ckpt.checkpoint_path(point.run_dir(outputs)))  # pruned
    resumed = read_record(partial.record_path(records))
    assert resumed["sessions"][0]["command"][3].startswith("resume=")
    assert [s for s, _ in resumed["scalars"]["eval/episode_reward"]] == [0, 100, 200]  # one run, continued
    assert (partial.run_dir(outputs) / "checkpoints" / "model_000000100.pt").is_file()
    assert campaign_main(["status", *args]) == 0
    assert "2 points (200 env steps each): 2 done" in capsys.readouterr().out
    assert campaign_main(["run", *args, "--hours", "1"]) == 0  # nothing left: nothing starts
    assert "campaign: 0 runs ended, 0 not started" in capsys.readouterr().out
    assert campaign_main(["report", *args, "--out", str(tmp_path / "report")]) == 0
    methods = [r["method"] for r in read_csv(tmp_path / "report" / "final.csv")]
    assert methods == ["qmix R_c=0", "qmix R_c=2"]


#: One point with small batches and the cpu budget: it checkpoints within seconds and never ends in a test.
SLOW_POINT = TWO_POINTS.replace("budget: smoke", "budget: cpu").replace("[0, 2]", "[0]") + (
    "overrides:\n  qmix: [train.num_envs=2, train.batch_episodes=2, train.replay_episodes=8, "
    "train.eval_episodes=2, train.eval_interval=100, train.checkpoint_interval=100, env.max_steps=10]\n"
)


def _running_members(pgid: int) -> list[int]:
    """PIDs of the processes of group ``pgid`` that are not zombies (from /proc)."""
    members = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue  # the process ended while we looked
        if int(fields[2]) == pgid and fields[0] != "Z":
            members.append(int(stat.parent.name))
    return members


def test_a_signal_stops_the_children_and_records_them_as_stopped(tmp_path: Path, capsys) -> None:
    matrix = tmp_path / "m.yaml"
    matrix.write_text(SLOW_POINT)
    (point,), _ = load_matrix(matrix)
    outputs, records = tmp_path / "outputs", tmp_path / "records"
    args = ["--matrix", str(matrix), "--outputs", str(outputs), "--records", str(records)]
    campaign = subprocess.Popen(
        [sys.executable, "-m", "mcrs_lab.campaign.cli", "run", *args, "--hours", "1"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    last = ckpt.checkpoint_path(point.run_dir(outputs))
    deadline = time.time() + 240
    while not last.is_file() and time.time() < deadline and campaign.poll() is None:
        time.sleep(0.5)
    assert last.is_file(), "the child never wrote a checkpoint"
    campaign.send_signal(signal.SIGTERM)
    out, _ = campaign.communicate(timeout=200)
    assert campaign.returncode == 128 + signal.SIGTERM, out
    assert "SIGTERM: stopping the running children" in out
    record = read_record(point.record_path(records))
    assert record["status"] == "stopped" and 100 <= record["checkpoint_env_steps"] < 200_000
    (session,) = [
        json.loads(line) for line in (point.run_dir(outputs) / "campaign.jsonl").read_text().splitlines()
    ]
    assert session["stopped_by_campaign"] and session["returncode"] == 128 + signal.SIGINT
    # the child saved at the stop (not only at its last step-based checkpoint) and said how to resume
    log = (point.run_dir(outputs) / "campaign.log").read_text()
    stop = [line for line in log.splitlines() if line.startswith("mcrs-train: SIGINT: stopped at env step ")]
    assert len(stop) == 1 and "Traceback" not in log, log
    assert int(stop[0].split("env step ")[1].split(",")[0]) == record["checkpoint_env_steps"]
    assert f"resume with: mcrs-train resume={point.run_dir(outputs)}" in log
    assert "replay_blocks" in ckpt.load(last)  # a stopped run is not pruned: it resumes next time
    # The child (its own process group) is gone: no member left but zombies (a container's PID 1 may
    # not reap the orphaned helpers the child had, such as multiprocessing's resource tracker).
    assert not _running_members(int(out.split("(pid ")[1].split(")")[0]))
    assert campaign_main(["run", *args, "--hours", "1", "--dry-run"]) == 0
    listing = capsys.readouterr().out
    assert listing.startswith(f"resume {point.id} (at {record['checkpoint_env_steps']} env steps, estimated ")


def test_fill_keeps_the_slots_busy_and_stops_the_runs_at_the_deadline(
    tmp_path: Path, capsys, monkeypatch
) -> None:
    matrix = tmp_path / "m.yaml"
    matrix.write_text(SLOW_POINT)
    (point,), _ = load_matrix(matrix)
    outputs, records = tmp_path / "outputs", tmp_path / "records"
    args = ["--matrix", str(matrix), "--outputs", str(outputs), "--records", str(records)]
    monkeypatch.setattr(runner, "FILL_FLOOR_S", 0.0)  # the budget below is under the 10-minute floor
    # 72 s: long enough for the child to be training when it is stopped, far too short for its budget.
    assert campaign_main(["run", *args, "--hours", "0.02", "--fill"]) == 0
    out = capsys.readouterr().out
    assert f"started {point.id} " in out and "campaign: the 0.02 h are over: stopping 1 runs (--fill)" in out
    assert "campaign: 0 runs ended, 1 stopped at the deadline (resumable), 0 not started" in out
    record = read_record(point.record_path(records))
    assert record["status"] == "stopped" and 0 < record["checkpoint_env_steps"] < 200_000
    (session,) = [
        json.loads(line) for line in (point.run_dir(outputs) / "campaign.jsonl").read_text().splitlines()
    ]
    assert session["stopped_by_campaign"] and session["returncode"] == 128 + signal.SIGINT
    assert "replay_blocks" in ckpt.load(ckpt.checkpoint_path(point.run_dir(outputs)))  # resumable
    assert campaign_main(["run", *args, "--hours", "1", "--dry-run"]) == 0
    assert capsys.readouterr().out.startswith(f"resume {point.id} (at {record['checkpoint_env_steps']} ")


def test_no_run_starts_that_the_time_budget_cannot_hold(tmp_path: Path, capsys) -> None:
    matrix = tmp_path / "m.yaml"
    matrix.write_text(TWO_POINTS)
    first, second = load_matrix(matrix)[0]
    outputs, records = tmp_path / "outputs", tmp_path / "records"
    earlier = {
        "format": RECORD_FORMAT,
        "version": RECORD_VERSION,
        "kind": "training",
        "run_dir": "x",
        "status": "finished",
        "checkpoint_env_steps": 100,  # 100 env steps in an hour: a 200-step point needs two
        "sessions": [{"wall_s": 3600.0}],
        **{k: v for k, v in RECORD_FIELDS.items() if k not in ("checkpoint_env_steps", "sessions")},
    }
    write_record(records / "comm_range" / "smoke" / "earlier.json", earlier)
    args = ["--matrix", str(matrix), "--outputs", str(outputs), "--records", str(records)]
    assert campaign_main(["run", *args, "--hours", "1.5", "--dry-run"]) == 0
    plan = capsys.readouterr().out  # the dry run applies the same rule as the run
    for point in (first, second):
        assert f"not started: {point.id} needs about 2.00 h, 1.50 h left" in plan
    assert campaign_main(["run", *args, "--hours", "3", "--dry-run", "--jobs", "1"]) == 0
    plan = capsys.readouterr().out  # one job: the second run would start at 2 h and end after 3 h
    assert (
        f"start {first.id} " in plan and f"not started: {second.id} needs about 2.00 h, 1.00 h left" in plan
    )
    assert campaign_main(["run", *args, "--hours", "1.5"]) == 0
    out = capsys.readouterr().out
    for point in (first, second):
        assert f"not started: {point.id} needs about 2.00 h, 1.50 h left" in out
        assert not point.run_dir(outputs).exists()
    assert "campaign: 0 runs ended, 2 not started (time budget)" in out
    # An algorithm with no record of its own is judged by the slowest recorded one on its map.
    write_record(records / "comm_range" / "smoke" / "earlier.json", {**earlier, "config": {
        "env": {"name": "map10"}, "algo": {"name": "vdn"}, "seed": 0}})  # fmt: skip
    assert campaign_main(["run", *args, "--hours", "1.5"]) == 0
    assert f"not started: {first.id} needs about 2.00 h, 1.50 h left" in capsys.readouterr().out
    # --fill: the budget is a hard stop; the first run starts though it cannot end in time, the second
    # would start when the slot frees at the deadline, under the floor a start needs.
    assert campaign_main(["run", *args, "--hours", "1.5", "--dry-run", "--jobs", "1", "--fill"]) == 0
    plan = capsys.readouterr().out
    assert f"start {first.id} (at 0 env steps, estimated 2.00 h, stopped at the deadline): " in plan
    assert f"not started: {second.id}: 0.00 h left, under the 0.17 h a start needs (--fill)" in plan
    assert plan.strip().endswith("runs going then are stopped and resume next time after 1.5 h")
    assert campaign_main(["run", *args, "--hours", "0.1", "--fill"]) == 0  # 6 minutes: under the floor
    out = capsys.readouterr().out
    assert f"not started: {first.id}: 0.10 h left, under the 0.17 h a start needs (--fill)" in out
    assert "campaign: 0 runs ended, 0 stopped at the deadline (resumable), 2 not started" in out
    assert not first.run_dir(outputs).exists()
    with open(outputs / ".campaign.lock", "a+") as lock:  # a campaign already running here
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(SystemExit, match="another mcrs-campaign run uses"):
            campaign_main(["run", *args, "--hours", "3"])


def test_finish_first_starts_the_runs_that_can_end_in_time_first_and_finish_only_starts_only_them(
    tmp_path: Path, capsys
) -> None:
    matrix = tmp_path / "m.yaml"
    matrix.write_text(TWO_POINTS.replace("algo: [qmix]", "algo: [qmix, vdn]").replace("[0, 2]", "[0]"))
    qmix, vdn = load_matrix(matrix)[0]
    records = tmp_path / "records"
    for algo, env_steps in (("qmix", 100), ("vdn", 400)):  # an hour each: a 200-step point needs 2 h, 0.5 h
        fields = {k: v for k, v in RECORD_FIELDS.items() if k not in ("checkpoint_env_steps", "sessions")}
        write_record(records / "comm_range" / "smoke" / f"earlier_{algo}.json", {
            "format": RECORD_FORMAT, "version": RECORD_VERSION, "kind": "training", "run_dir": "x",
            "status": "finished", "checkpoint_env_steps": env_steps, "sessions": [{"wall_s": 3600.0}],
            **fields, "config": {"env": {"name": "map10"}, "algo": {"name": algo}, "seed": 0}})  # fmt: skip
    args = ["--matrix", str(matrix), "--outputs", str(tmp_path / "o"), "--records", str(records)]
    args += ["--hours", "1", "--jobs", "1", "--fill", "--dry-run"]
    assert campaign_main(["run", *args]) == 0
    plan = capsys.readouterr().out.splitlines()
    assert plan[0].startswith(f"start {qmix.id} (at 0 env steps, estimated 2.00 h, stopped at the deadline)")
    assert plan[1] == f"not started: {vdn.id}: 0.00 h left, under the 0.17 h a start needs (--fill)"
    assert campaign_main(["run", *args, "--finish-first"]) == 0
    plan = capsys.readouterr().out.splitlines()
    assert plan[0].startswith(f"start {vdn.id} (at 0 env steps, estimated 0.50 h): ")
    assert plan[1].startswith(f"start {qmix.id} (at 0 env steps, estimated 2.00 h, stopped at the deadline)")
    assert (
        plan[-1]
        == "2 runs, 1 at a time, those that can end in time first, runs going then are stopped and resume next time after 1 h"
    )
    with pytest.raises(SystemExit, match="--finish-first needs --fill"):
        campaign_main(["run", *[a for a in args if a != "--fill"], "--finish-first"])
    # --finish-only: the run that cannot end in time is not started, in the plan and in the run
    assert campaign_main(["run", *args, "--finish-only"]) == 0
    plan = capsys.readouterr().out.splitlines()
    assert plan[0].startswith(f"start {vdn.id} (at 0 env steps, estimated 0.50 h): ")
    assert plan[1] == f"not started: {qmix.id} needs about 2.00 h, 0.50 h left (--finish-only)"
    assert plan[-1].startswith("2 runs, 1 at a time, only those that can end in time (and partial ones), ")
    with pytest.raises(SystemExit, match="--finish-only needs --fill"):
        campaign_main(["run", *[a for a in args if a != "--fill"], "--finish-only"])
    run_args = [a for a in args if a != "--dry-run"]
    run_args[run_args.index("--hours") + 1] = "0.4"  # under vdn's 0.5 h too: nothing starts, nothing is made
    assert campaign_main(["run", *run_args, "--finish-only"]) == 0
    out = capsys.readouterr().out
    assert f"not started: {vdn.id} needs about 0.50 h, 0.40 h left (--finish-only)" in out
    assert f"not started: {qmix.id} needs about 2.00 h, 0.40 h left (--finish-only)" in out
    assert "campaign: 0 runs ended, 0 stopped at the deadline (resumable), 2 not started" in out
    assert not qmix.run_dir(tmp_path / "o").exists() and not vdn.run_dir(tmp_path / "o").exists()


def test_threads_reach_every_command_and_the_cores_bound_them(tmp_path: Path, capsys) -> None:
    matrix = tmp_path / "m.yaml"
    matrix.write_text(TWO_POINTS)
    first, _ = load_matrix(matrix)[0]
    args = ["--matrix", str(matrix), "--outputs", str(tmp_path / "o"), "--records", str(tmp_path / "r")]
    cores = os.cpu_count() or 1
    assert (
        campaign_main(["run", *args, "--hours", "1", "--jobs", "1", "--threads", str(cores), "--dry-run"])
        == 0
    )
    starts = [line for line in capsys.readouterr().out.splitlines() if line.startswith("start ")]
    assert len(starts) == 2 and all(f" threads={cores} " in line for line in starts)
    assert "threads=2" in first.resume_command(tmp_path, 100, threads=2)
    with pytest.raises(
        SystemExit, match=rf"--threads={cores + 1}: must be >= 1, with --jobs x --threads <= {cores}"
    ):
        campaign_main(["run", *args, "--hours", "1", "--jobs", "1", "--threads", str(cores + 1), "--dry-run"])
    with pytest.raises(SystemExit, match=r"--threads=0: must be >= 1"):
        campaign_main(["run", *args, "--hours", "1", "--jobs", "1", "--threads", "0", "--dry-run"])


EVALUATION = """
evaluations:
  shield:
    of: [figa]
    heuristics: [greedy]
    episodes: 2
    seeds: [0, 1]
    variants:
      "on": [env.no_fly_shield=true]
      "off": [env.no_fly_shield=false]
"""


def test_the_section6_near_file_evaluates_figure_7_with_and_without_the_shield() -> None:
    from mcrs_lab.campaign.evaluations import load_evaluations

    _, titles = load_matrix(NEAR_MATRIX)
    (shield,) = load_evaluations(NEAR_MATRIX, set(titles))
    assert (shield.name, shield.of, shield.heuristics, shield.episodes) == (
        "shield",
        ("fig7",),
        ("greedy",),
        32,
    )
    assert dict(shield.variants) == {"on": ("env.no_fly_shield=true",), "off": ("env.no_fly_shield=false",)}


def test_overrides_for_all_points_reach_every_run_and_the_heuristics_evaluations(
    tmp_path: Path, capsys
) -> None:
    matrix = tmp_path / "m.yaml"
    matrix.write_text(
        TWO_POINTS + "overrides:\n  all: [env.safety_rule=near]\n  qmix: [algo.double_q=false]\n" + EVALUATION
    )
    points, _ = load_matrix(matrix)
    assert all(p.overrides == ("env.safety_rule=near", "algo.double_q=false") for p in points)
    assert "env.safety_rule=near" in points[0].train_command(tmp_path)
    records = tmp_path / "records"
    finished = points[0]
    ckpt.checkpoint_path(tmp_path / "run").parent.mkdir(parents=True)
    ckpt.checkpoint_path(tmp_path / "run").write_bytes(b"")  # a run directory the dry run could evaluate
    finished.record_path(records).parent.mkdir(parents=True)
    finished.record_path(records).write_text(
        json.dumps(
            {
                "format": RECORD_FORMAT,
                "version": RECORD_VERSION,
                "kind": "training",
                "status": "finished",
                "run_dir": str(tmp_path / "run"),
                # the fields every record has (mcrs_lab.analysis.record_schema refuses a record without them)
                "total_env_steps": 40,
                "checkpoint_env_steps": 40,
                "final_eval": {},
                "config": {"env": {"name": "map10"}, "algo": {"name": "qmix"}, "seed": 0},
                "scalars": {},
            }
        )
    )
    args = ["--matrix", str(matrix), "--outputs", str(tmp_path / "o"), "--records", str(records)]
    capsys.readouterr()
    assert campaign_main(["evaluate", *args, "--dry-run"]) == 0
    commands = [line for line in capsys.readouterr().out.splitlines() if line.startswith("evaluate ")]
    assert commands and all("env.safety_rule=near" in line for line in commands)
    assert any(f"policy={tmp_path / 'run'} " in line for line in commands)  # the record's path
    # The same run under --outputs (moved, or run from another directory): found there first.
    moved = finished.run_dir(tmp_path / "o")
    ckpt.checkpoint_path(moved).parent.mkdir(parents=True)
    ckpt.checkpoint_path(moved).write_bytes(b"")
    assert campaign_main(["evaluate", *args, "--dry-run"]) == 0
    commands = [line for line in capsys.readouterr().out.splitlines() if line.startswith("evaluate ")]
    assert any(f"policy={moved} " in line for line in commands)
    assert not any(f"policy={tmp_path / 'run'} " in line for line in commands)


def _evaluation_record(policy: str, seed: int, run: str | None) -> dict:
    row = {"policy": policy, "env": "map20", "comm_range": 5.0, "seed": seed, "episodes": 2,
           "means": {"episode_reward": 300.0}, "label": "trained qmix"}  # fmt: skip
    if run is not None:
        row["run"] = run
    return {"format": RECORD_FORMAT, "version": RECORD_VERSION, "kind": "evaluation", "run_dir": "eval",
            "study": "eval", "policy": policy, "config": {}, "rows": [row]}  # fmt: skip


def test_two_experiments_runs_of_one_folder_name_are_evaluated_and_reported_apart(tmp_path: Path) -> None:
    from mcrs_lab.analysis.evaluations import trained_rows
    from mcrs_lab.analysis.records import evaluation_record_path
    from mcrs_lab.analysis.runs import find_runs
    from mcrs_lab.campaign.evaluations import Evaluation, EvaluationJob

    evaluation = Evaluation("shields_eval", "", ("f",), ("greedy",), 2, (0, 1), (("both", ()),))
    jobs = {
        experiment: EvaluationJob(
            evaluation,
            "both",
            (),
            "map20",
            f"/o/{experiment}/campaign/map20_qmix_seed0",
            f"{experiment}/map20_qmix_seed0",
        )
        for experiment in ("shields_gamma", "shields_view")
    }
    records = tmp_path / "records"
    gamma = [
        _evaluation_record(jobs["shields_gamma"].policy, s, "shields_gamma/map20_qmix_seed0") for s in (0, 1)
    ]
    for record in gamma:
        path = evaluation_record_path(records / "shields_eval" / "both", record)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(record))
    assert path.name == "trained-qmix-shields_gamma-map20_qmix_seed0_rc5_seed1.json"
    assert jobs["shields_gamma"].recorded(records) and not jobs["shields_view"].recorded(records)
    # A record made before the run's experiment was kept names the folder alone: it counts for the point
    # whose experiment its policy path runs through, and only for that one.
    legacy = _evaluation_record("/w/outputs/campaign/shields_view/campaign/map20_qmix_seed0", 0, None)
    legacy_path = evaluation_record_path(records / "shields_eval" / "both", legacy)
    assert legacy_path.name == "trained-qmix-map20_qmix_seed0_rc5_seed0.json"
    legacy_path.write_text(json.dumps(legacy))
    assert not jobs["shields_view"].recorded(records)  # seed 1 is still missing
    legacy_path.with_name("trained-qmix-map20_qmix_seed0_rc5_seed1.json").write_text(
        json.dumps(_evaluation_record(legacy["policy"], 1, None))
    )
    assert jobs["shields_view"].recorded(records) and jobs["shields_gamma"].recorded(records)
    # The report: two methods, not one method of four runs.
    methods = {row["method"]: row["seeds"] for row in trained_rows(find_runs([records]).evaluations)}
    assert methods == {"trained qmix [shields_gamma/map20_qmix]": 1, "trained qmix [map20_qmix]": 1}, methods


def test_evaluate_records_finished_policies_and_the_heuristics_once(tmp_path: Path, capsys) -> None:
    matrix = tmp_path / "m.yaml"
    matrix.write_text(TWO_POINTS + EVALUATION)
    finished, unfinished = load_matrix(matrix)[0]
    outputs, records = tmp_path / "outputs", tmp_path / "records"
    args = ["--matrix", str(matrix), "--outputs", str(outputs), "--records", str(records)]
    assert campaign_main(["run", *args, "--hours", "1", "--only", finished.id, "--no-evaluate"]) == 0
    assert read_record(finished.record_path(records))["status"] == "finished"
    assert not records.joinpath("shield").exists()  # --no-evaluate: trained and recorded only
    capsys.readouterr()
    assert campaign_main(["evaluate", *args, "--dry-run"]) == 0
    plan = capsys.readouterr().out.splitlines()
    assert plan[0] == f"not evaluated: {unfinished.id}: no record of a finished run"
    assert [line.split(":")[0] for line in plan[1:]] == [
        "evaluate shield/on greedy",
        f"evaluate shield/on {finished.id}",
        "evaluate shield/off greedy",
        f"evaluate shield/off {finished.id}",
    ]
    assert "env=map10 env.comm_range=0 env.no_fly_shield=false episodes=2 seed=0,1 figures=false" in plan[-1]
    assert not records.joinpath("shield").exists()  # a dry run runs nothing
    assert campaign_main(["evaluate", *args]) == 0
    out = capsys.readouterr().out
    assert "evaluations: 4 run, 0 failed, 1 points not evaluated" in out
    trained_name = f"trained-qmix-comm_range-{finished.name}"  # its algorithm, experiment and run folder
    for variant, shield in (("on", True), ("off", False)):
        folder = records / "shield" / variant / "eval" / "map10"
        names = sorted(p.name for p in folder.glob("*.json"))
        assert names == [
            "greedy_rc5_seed0.json",
            "greedy_rc5_seed1.json",
            f"{trained_name}_rc0_seed0.json",  # at the R_c it was trained with
            f"{trained_name}_rc0_seed1.json",
        ], names
        for path in folder.glob("*.json"):
            record = read_record(path)
            assert record["config"]["env"]["no_fly_shield"] is shield and record["config"]["episodes"] == 2
        trained = read_record(folder / f"{trained_name}_rc0_seed1.json")
        assert trained["policy"] == str(finished.run_dir(outputs)) and trained["rows"][0]["seed"] == 1
        assert trained["rows"][0]["run"] == finished.id
    # The shield keeps the UAVs out of the no-fly zones: no violation with it, on the same episodes.
    on = read_record(records / "shield/on/eval/map10" / f"{trained_name}_rc0_seed0.json")
    assert on["rows"][0]["means"]["no_fly_violations"] == 0
    assert campaign_main(["evaluate", *args]) == 0  # everything recorded: nothing runs again
    out = capsys.readouterr().out
    assert "evaluations: 0 run, 0 failed, 1 points not evaluated" in out
    assert f"recorded: shield/off {finished.id}" in out
    assert campaign_main(["status", *args]) == 0
    out = capsys.readouterr().out
    assert (
        "evaluation shield: 4 of 4 (policy, variant) evaluations recorded, 1 points not evaluable yet" in out
    )
    # A fresh clone has the records, not the run directories: what is recorded still counts.
    moved = tmp_path / "moved"
    finished.run_dir(outputs).rename(moved)
    assert campaign_main(["status", *args]) == 0
    out = capsys.readouterr().out
    assert (
        "evaluation shield: 4 of 4 (policy, variant) evaluations recorded, 1 points not evaluable yet" in out
    )
    off = records / "shield/off/eval/map10" / f"{trained_name}_rc0_seed1.json"
    off.unlink()  # a variant to evaluate again, and no run directory to evaluate
    assert campaign_main(["evaluate", *args, "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert f"not evaluated: {finished.id}: its run directory {finished.run_dir(outputs)} is not here" in out
    assert f"recorded: shield/on {finished.id}" in out and f"shield/off {finished.id}" not in out
    moved.rename(finished.run_dir(outputs))
    assert campaign_main(["evaluate", *args]) == 0  # back: the variant missing a seed runs again
    assert "evaluations: 1 run, 0 failed, 1 points not evaluated" in capsys.readouterr().out
    assert off.is_file()
    # `run` evaluates each run that finishes, as the file asks
    assert campaign_main(["run", *args, "--hours", "1", "--only", unfinished.id]) == 0
    out = capsys.readouterr().out
    assert f"evaluated shield/on {unfinished.id}:" in out and f"evaluated shield/off {unfinished.id}:" in out
    assert "greedy" not in out  # already recorded on this map
    for variant in ("on", "off"):
        folder = records / "shield" / variant / "eval" / "map10"
        assert len(list(folder.glob(f"trained-qmix-comm_range-{unfinished.name}_rc2_seed[01].json"))) == 2
    with pytest.raises(SystemExit, match=r"--evaluation=nope: allowed values are shield"):
        campaign_main(["evaluate", *args, "--evaluation", "nope"])
    matrix.write_text(TWO_POINTS + EVALUATION.replace("of: [figa]", "of: [fig7]"))
    with pytest.raises(
        SystemExit, match=r"evaluation shield: of=\['fig7'\]: name figures of the file \(figa\)"
    ):
        campaign_main(["evaluate", *args])
    matrix.write_text(TWO_POINTS + EVALUATION.replace("episodes: 2", "episodes: 0"))
    with pytest.raises(SystemExit, match=r"evaluation shield: episodes=0: a whole number >= 1"):
        campaign_main(["evaluate", *args])
    matrix.write_text(TWO_POINTS + EVALUATION.replace("seeds: [0, 1]", "seeds: [zero]"))
    with pytest.raises(
        SystemExit, match=r"evaluation shield: seeds=\['zero'\]: whole numbers in \[0, 2\*\*63 - 1\]"
    ):
        campaign_main(["evaluate", *args])
    matrix.write_text(TWO_POINTS + EVALUATION.replace('"on"', "on"))
    with pytest.raises(SystemExit, match=r"evaluation shield: variant True: not a name \(YAML reads"):
        campaign_main(["evaluate", *args])


def test_a_point_in_use_by_a_live_run_is_not_started_and_the_exit_status_says_so(
    tmp_path: Path, capsys
) -> None:
    """A refused point is not 'all is well': one line per point, the count, exit status 1 (issue 33)."""
    from mcrs.experiment.run.rundir import RunLock

    matrix = tmp_path / "m.yaml"
    matrix.write_text(TWO_POINTS.replace("[0, 2]", "[0]"))
    (point,), _ = load_matrix(matrix)
    outputs, records = tmp_path / "outputs", tmp_path / "records"
    lock = RunLock(point.run_dir(outputs))  # a user's mcrs-train on the point, before its first checkpoint
    try:
        args = ["--matrix", str(matrix), "--outputs", str(outputs), "--records", str(records)]
        assert campaign_main(["run", *args, "--hours", "1", "--jobs", "1"]) == 1
    finally:
        lock.release()
    out = capsys.readouterr().out
    assert f"not started: {point.id}: its run directory {point.run_dir(outputs)} is in use by process" in out
    assert (
        "campaign: 1 runs not started: another campaign trains them, or their directories are in use or "
        "not the campaign's (exit status 1)" in out
    )
    assert not (point.run_dir(outputs) / "campaign.log").exists()


def test_a_point_another_campaign_trains_is_not_started_whatever_its_outputs(tmp_path: Path, capsys) -> None:
    """Two runners recording into one folder with different --outputs must not train one point twice."""
    matrix = tmp_path / "m.yaml"
    matrix.write_text(TWO_POINTS.replace("[0, 2]", "[0]"))
    (point,), _ = load_matrix(matrix)
    records, theirs, ours = tmp_path / "records", tmp_path / "theirs", tmp_path / "ours"
    held = runner.claim_point(records, point, theirs)  # the other runner, training the point now
    assert not isinstance(held, str)
    holder = f"pid {os.getpid()}, outputs {theirs.resolve()}"
    args = ["--matrix", str(matrix), "--outputs", str(ours), "--records", str(records)]
    try:
        assert campaign_main(["run", *args, "--hours", "1", "--jobs", "1"]) == 1
        assert (
            f"not started: {point.id}: another mcrs-campaign run trains it ({holder}; "
            f"{runner.claim_path(records, point)}); its record lands in {records}" in capsys.readouterr().out
        )
        assert runner.claim_point(records, point, ours) == holder
        record = {"format": RECORD_FORMAT, "version": RECORD_VERSION, "kind": "training", "run_dir": "x",
                  **RECORD_FIELDS, "status": "stopped", "checkpoint_env_steps": 50}  # fmt: skip
        write_record(point.record_path(records), record)  # their earlier stop; its checkpoint is in theirs
        assert campaign_main(["status", *args]) == 0  # status says who trains it, not that it starts over
        out = capsys.readouterr().out
        assert f"training now: {holder}; a stopped record at 50 steps of x |" in out
        assert "starts from 0" not in out
    finally:
        held.close()
    assert not point.run_dir(ours).exists()
    assert runner.claim_holder(records, point) is None
    assert campaign_main(["status", *args]) == 0
    out = capsys.readouterr().out
    assert "training now" not in out and "a stopped record at 50 steps of x, no checkpoint of it here" in out
    again = runner.claim_point(records, point, ours)  # released: free again
    assert not isinstance(again, str)
    again.close()


def test_a_point_recorded_since_the_plan_was_made_is_not_started(tmp_path: Path, capsys) -> None:
    matrix = tmp_path / "m.yaml"
    matrix.write_text(TWO_POINTS.replace("[0, 2]", "[0]"))
    (point,), _ = load_matrix(matrix)
    records = tmp_path / "records"
    campaign = runner.Campaign([point], tmp_path / "outputs", records, total_env_steps=200, jobs=1)
    _, [(state, command)] = campaign.plan()
    assert state.state == "missing"
    write_record(point.record_path(records), {  # another runner finished it meanwhile
        "format": RECORD_FORMAT, "version": RECORD_VERSION, "kind": "training", "run_dir": "elsewhere",
        "status": "finished", **RECORD_FIELDS})  # fmt: skip
    assert campaign._launch(state, command) is None
    assert f"not started: {point.id}: done meanwhile (its record in {records})" in capsys.readouterr().out
    assert not point.run_dir(tmp_path / "outputs").exists()
    free = runner.claim_point(records, point, tmp_path / "outputs")
    assert not isinstance(free, str)
    free.close()
