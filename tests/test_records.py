"""Records of real smoke runs: what they hold, that the report from records alone equals the report from
the run directories, pruning, and the heuristic reference lines of the learning curves."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from mcrs.experiment.run import checkpoint as ckpt
from mcrs_lab.analysis.evaluations import heuristic_references
from mcrs_lab.analysis.records import make_record, write_record
from mcrs_lab.analysis.report import main as report_main
from mcrs_lab.analysis.runs import find_runs
from mcrs_lab.campaign.cli import main as campaign_main
from mcrs_lab.campaign.matrix import DEFAULT_MATRIX
from tests.test_report import make_evaluation, make_run, read_csv

pytestmark = pytest.mark.slow

REPORT_FILES = ("final.csv", "milestones.csv", "comm_range.csv", "final.md", "milestones.md", "report.md")


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two real QMIX smoke runs at R_c 0 and 5 on map10 (the second resumed to 400 env steps) and the
    heuristics on map10 over two evaluation seeds, as the commands leave them."""
    root = tmp_path_factory.mktemp("runs")
    train = subprocess.run(
        [
            sys.executable,
            "-m",
            "mcrs.train",
            "experiment=comm_range",
            "budget=smoke",
            "env=map10",
            "env.comm_range=0,5",
            f"hydra.sweep.dir={root / 'train'}",
        ],
        cwd=root,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert train.returncode == 0, train.stderr[-3000:]
    resumed = root / "train" / "map10_qmix_rc5_seed0"
    more = subprocess.run(  # a second session: the record must sum both sessions' time
        [sys.executable, "-m", "mcrs.train", f"resume={resumed}", "train.total_env_steps=400"],
        cwd=root,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert more.returncode == 0, more.stderr[-3000:]
    heuristics = subprocess.run(
        [
            sys.executable,
            "-m",
            "mcrs.evaluate",
            "study=heuristics",
            "env=map10",
            "seed=0,1",
            "episodes=2",
            "env.max_steps=5",
            f"hydra.sweep.dir={root / 'heuristics'}",
        ],
        cwd=root,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert heuristics.returncode == 0, heuristics.stderr[-3000:]
    return root


def test_record_of_a_real_run_holds_the_evidence(runs: Path, tmp_path: Path) -> None:
    run_dir = runs / "train" / "map10_qmix_rc5_seed0"
    path, record = make_record(run_dir, tmp_path / "records")
    assert path == tmp_path / "records" / "comm_range" / "smoke" / "map10_qmix_rc5_seed0.json"
    assert (record["status"], record["checkpoint_env_steps"], record["total_env_steps"]) == (
        "finished",
        400,
        400,
    )
    assert record["config"]["env"]["comm_range"] == 5.0 and record["config"]["algo"]["name"] == "qmix"
    reward = (run_dir / "logs" / "scalars" / "eval" / "episode_reward.csv").read_text().split()
    logged = {int(s): float(v) for s, v in (line.split(",") for line in reward)}
    assert dict(map(tuple, record["scalars"]["eval/episode_reward"])) == logged  # the curve, exactly
    assert record["final_eval"]["env_step"] == 400
    assert record["final_eval"]["episode_reward"] == logged[400]
    assert "train/q_taken_mean" in record["scalars"] and "eval/no_fly_violations" in record["scalars"]
    # two sessions (to 200 steps, then resumed to 400), each with its own clock: both are added
    folder = run_dir / "logs" / "scalars" / "time"
    clocks = {
        p.stem: dict(line.split(",") for line in p.read_text().split())
        for p in folder.glob("*_s.csv")
        if p.stem != "env_steps_per_s"
    }
    assert all(list(c) == ["100", "200", "400"] for c in clocks.values())
    expected = sum(float(c["200"]) + float(c["400"]) for c in clocks.values())
    assert record["loop_time_s"] == round(expected, 1) > 0
    machine = record["recorded"]["machine"]
    assert machine["cpu_count"] >= 1 and machine["torch"] == torch.__version__
    assert machine["cpu_capability"] == torch.backends.cpu.get_cpu_capability()  # its kernels: its roundings
    assert len(record["recorded"]["git"]["commit"]) == 40
    assert write_record(path, record) == "written"
    assert path.stat().st_size < 50_000


def test_recording_twice_changes_nothing_and_another_run_is_not_overwritten(
    runs: Path, tmp_path: Path
) -> None:
    run_dir = runs / "train" / "map10_qmix_rc0_seed0"
    assert campaign_main(["record", str(run_dir), "--records", str(tmp_path)]) == 0
    path = tmp_path / "comm_range" / "smoke" / "map10_qmix_rc0_seed0.json"
    first = path.read_bytes()
    assert write_record(path, make_record(run_dir, tmp_path)[1]) == "unchanged"
    assert path.read_bytes() == first  # not even the record time changes
    other = json.loads(first)
    other["run_dir"] = "elsewhere/map10_qmix_rc0_seed0"
    with pytest.raises(ValueError, match="records another run"):
        write_record(path, other)
    assert write_record(path, other, replace=True) == "updated"


def test_a_campaign_file_chooses_where_a_hand_made_record_goes(
    runs: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--matrix`` puts the record under that file's records root (the paper's: results/records/paper),
    none keeps results/records, and ``--records`` wins over both."""
    run_dir = runs / "train" / "map10_qmix_rc0_seed0"
    monkeypatch.chdir(tmp_path)
    point = Path("comm_range", "smoke", "map10_qmix_rc0_seed0.json")
    assert campaign_main(["record", str(run_dir), "--matrix", str(DEFAULT_MATRIX)]) == 0
    assert [p.relative_to(tmp_path) for p in tmp_path.rglob("*.json")] == [
        Path("results/records/paper") / point
    ]
    assert campaign_main(["record", str(run_dir)]) == 0
    assert (tmp_path / "results" / "records" / point).is_file()
    assert campaign_main(["record", str(run_dir), "--matrix", str(DEFAULT_MATRIX), "--records", "mine"]) == 0
    assert (tmp_path / "mine" / point).is_file()


def test_a_record_changed_while_it_is_rewritten_is_kept(
    runs: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Another process writes the point's record between this one's read and its write: that record is
    kept, and this one is refused in one line (the edit is never written over)."""
    import mcrs_lab.analysis.records as records

    run_dir = runs / "train" / "map10_qmix_rc0_seed0"
    assert campaign_main(["record", str(run_dir), "--records", str(tmp_path)]) == 0
    path = tmp_path / "comm_range" / "smoke" / "map10_qmix_rc0_seed0.json"
    other = json.loads(path.read_bytes())
    other["run_dir"] = "elsewhere/map10_qmix_rc0_seed0"
    real_dumps = records.dumps

    def meanwhile(record):
        path.write_text('{"written": "meanwhile"}')  # the other process's record lands now
        return real_dumps(record)

    monkeypatch.setattr(records, "dumps", meanwhile)
    with pytest.raises(ValueError, match="changed since it was read: nothing written"):
        write_record(path, other, replace=True)
    assert path.read_text() == '{"written": "meanwhile"}'
    assert not [p.name for p in path.parent.iterdir() if p.name != path.name]  # no temporary left


def test_report_from_records_alone_equals_the_report_from_run_directories(runs: Path, tmp_path: Path) -> None:
    records = tmp_path / "records"
    dirs = sorted((runs / "train").glob("map10_*")) + sorted((runs / "heuristics").glob("seed*"))
    assert len(dirs) == 4
    assert campaign_main(["record", *map(str, dirs), "--records", str(records)]) == 0
    assert sorted(p.relative_to(records).as_posix() for p in records.rglob("*.json")) == [
        "comm_range/smoke/map10_qmix_rc0_seed0.json",
        "comm_range/smoke/map10_qmix_rc5_seed0.json",
        "heuristics/map10/all_rc5_seed0.json",
        "heuristics/map10/all_rc5_seed1.json",
    ]
    from_dirs, from_records = tmp_path / "from_dirs", tmp_path / "from_records"
    assert report_main([str(runs / "train"), str(runs / "heuristics"), "--out", str(from_dirs)]) == 0
    copied = tmp_path / "elsewhere"  # no run directory in reach: only the JSON files
    copied.mkdir()
    for record in records.rglob("*.json"):
        (copied / record.name).write_bytes(record.read_bytes())
    assert report_main([str(copied), "--out", str(from_records)]) == 0
    for name in REPORT_FILES:
        assert (from_records / name).read_text() == (from_dirs / name).read_text(), name
    assert [r["method"] for r in read_csv(from_records / "final.csv")] == [
        "qmix R_c=0",
        "qmix R_c=5",
        "random (heuristic)",
        "lawnmower (heuristic)",
        "greedy (heuristic)",
        "coverage (heuristic)",
    ]
    # given both, a run counts once: the record of a directory that is read itself is skipped
    both = find_runs([runs / "train", records])
    assert len(both.training) == 2 and len(both.evaluations) == 8  # 2 seeds x 4 heuristics
    assert sum("which is read itself" in s.reason for s in both.skipped) == 2


def test_prune_keeps_the_weights_and_drops_the_replay(runs: Path, tmp_path: Path) -> None:
    source = runs / "train" / "map10_qmix_rc0_seed0"
    run_dir = tmp_path / "run"
    subprocess.run(["cp", "-r", str(source), str(run_dir)], check=True)
    before = ckpt.load(ckpt.checkpoint_path(run_dir))
    assert before["replay_blocks"]["length"] > 0  # last.pt names the replay's block files
    assert list((run_dir / "checkpoints").glob("replay_*_*.pt"))
    assert campaign_main(["record", str(run_dir), "--records", str(tmp_path / "r"), "--prune"]) == 0
    after = ckpt.load(ckpt.checkpoint_path(run_dir))
    assert "replay_blocks" not in after and after["pruned"]["dropped"] == ["replay_blocks"]
    assert not list((run_dir / "checkpoints").glob("replay_*_*.pt"))  # the block files are gone too
    assert after["counters"] == before["counters"]
    for name, tensor in before["learner"]["agent"].items():
        assert torch.equal(after["learner"]["agent"][name], tensor)
    assert ckpt.checkpoint_path(run_dir).stat().st_size <= after["pruned"]["bytes_before"]
    assert (run_dir / "checkpoints" / "model_000000200.pt").is_file()
    assert ckpt.prune_bulk(run_dir)[0] == ckpt.prune_bulk(run_dir)[1]  # nothing left to drop
    assert not list((run_dir / "checkpoints").glob(".*.tmp"))
    resumed = subprocess.run(
        [sys.executable, "-m", "mcrs.train", f"resume={run_dir}", "train.total_env_steps=400"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert "no replay buffer" in resumed.stderr  # a pruned run is evidence, not a resumable run


@pytest.mark.parametrize("layout", ["callbacks", "legacy"])
def test_prune_drops_the_episodic_memory_entries_but_keeps_the_embedding(tmp_path: Path, layout: str) -> None:
    memory = {"memory": {"keys": torch.zeros(1000, 4)}, "embedding": {"w": torch.ones(2)}}
    state = {
        "counters": {"env_steps": 10},
        "config": {},
        "learner": {"agent": {"w": torch.ones(3)}},
        "replay": {"length": 1, "episodes": {"obs": torch.zeros(100)}},
        **({"callbacks": {"memory": memory}} if layout == "callbacks" else {"episodic": memory}),
    }
    ckpt.save_atomic(state, ckpt.checkpoint_path(tmp_path))
    ckpt.prune_bulk(tmp_path)
    after = ckpt.load(ckpt.checkpoint_path(tmp_path))
    kept = after["callbacks"]["memory"] if layout == "callbacks" else after["episodic"]
    assert set(kept) == {"embedding"} and "replay" not in after
    dotted = "callbacks.memory.memory" if layout == "callbacks" else "episodic.memory"
    assert after["pruned"]["dropped"] == ["replay", dotted]
    assert torch.equal(kept["embedding"]["w"], torch.ones(2))


def test_a_stopped_run_is_recorded_as_stopped_and_not_pruned(runs: Path, tmp_path: Path, capsys) -> None:
    source = runs / "train" / "map10_qmix_rc0_seed0"
    run_dir = tmp_path / "run"
    subprocess.run(["cp", "-r", str(source), str(run_dir)], check=True)
    state = ckpt.load(ckpt.checkpoint_path(run_dir))
    state["config"]["train"]["total_env_steps"] = 1000  # as if extended and killed at 200
    ckpt.save_atomic(
        {k: v for k, v in state.items() if k not in ("format", "version")}, ckpt.checkpoint_path(run_dir)
    )
    assert campaign_main(["record", str(run_dir), "--records", str(tmp_path / "r"), "--prune"]) == 0
    out = capsys.readouterr().out
    assert "(stopped at 200 env steps)" in out and "not pruned" in out
    assert "replay_blocks" in ckpt.load(ckpt.checkpoint_path(run_dir))  # still resumable


def test_record_refuses_what_is_not_a_run(tmp_path: Path, capsys) -> None:
    assert campaign_main(["record", str(tmp_path), "--records", str(tmp_path / "r")]) == 1
    assert "neither an mcrs-train run (config.yaml) nor an mcrs-eval result" in capsys.readouterr().err


def test_learning_curves_carry_the_heuristics_as_lines(tmp_path: Path) -> None:
    for seed in range(2):
        make_run(tmp_path, f"qmix_{seed}", seed=seed)
    for seed in range(3):  # greedy over 3 evaluation seeds; random only at another R_c (not drawn)
        make_evaluation(tmp_path, f"greedy_{seed}", "greedy", 5.0, seed, found=3 + seed)
    make_evaluation(tmp_path, "random_rc0", "random", 0.0, 0, found=1)
    references = heuristic_references(find_runs([tmp_path]).evaluations, 5.0)
    (greedy_targets,) = references["targets found"]
    got = (greedy_targets.label, greedy_targets.count, greedy_targets.over, greedy_targets.mean)
    assert got == ("greedy (heuristic)", 3, "evaluation seeds", 4.0)
    assert greedy_targets.half_width == pytest.approx(4.303 / 3**0.5, rel=1e-3)  # t(0.975, 2) * 1 / sqrt(3)
    assert references["episode reward"][0].mean == pytest.approx(40.0)
    out = tmp_path / "report"
    report_main([str(tmp_path), "--out", str(out)])
    text = (out / "report.md").read_text()
    assert "Horizontal lines: the heuristics greedy (3 evaluation seeds), mean and 95 % band." in text
    without = tmp_path / "without"
    report_main([str(tmp_path / "qmix_0"), str(tmp_path / "qmix_1"), "--out", str(without)])
    assert "No heuristic lines" in (without / "report.md").read_text()
    assert (out / "learning_curves.png").read_bytes() != (without / "learning_curves.png").read_bytes()


def test_every_committed_record_lies_where_its_content_puts_it() -> None:
    """``mcrs-campaign status`` and the evaluations find a point's record by the path its content gives
    (``training_record_path``, ``evaluation_record_path``): a record saved under another name (a copy made
    by hand) would leave its point "missing" and be counted again beside the next one."""
    from mcrs_lab.analysis.records import RECORDS_DIR, evaluation_record_path, training_record_path
    from mcrs_lab.analysis.runs import read_record

    root = Path(__file__).resolve().parents[1] / RECORDS_DIR
    paths = sorted(root.rglob("*.json"))
    assert len(paths) > 300  # figure 7's, table 4's, the heuristics', the near campaign's and the probes'
    misplaced = []
    for path in paths:
        record = read_record(path)
        assert record is not None, f"{path}: not a record of this version"
        study_root = path.parents[2]  # <root>/<experiment>/<budget>/<point>, <root>/<study>/<map>/<policy>
        if record["kind"] == "training":
            expected = training_record_path(study_root, record["config"])
        else:
            expected = evaluation_record_path(study_root, record)
        if expected != path:
            misplaced.append(f"{path.relative_to(root)} (belongs at {expected.relative_to(root)})")
    assert not misplaced, misplaced
