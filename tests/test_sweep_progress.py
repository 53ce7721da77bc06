"""A Hydra sweep says how far it is after each job ("k of n done, ETA") and ends with one table (a row per
job: overrides, final evaluation reward, no-fly violations, wall time, status) printed and written to
``<sweep dir>/sweep_summary.md`` (mcrs.experiment.commands.sweep, the ``sweep_progress`` callback of mcrs-train and
mcrs-eval)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
from hydra.core.utils import JobStatus
from hydra.types import RunMode
from omegaconf import OmegaConf

from mcrs.experiment.commands.sweep import STATE_DIR, SUMMARY, SweepProgress, clock, sweep_size
from tests.train_helpers import TINY


def _config(sweep: Path, num: int = 0, task: list[str] | None = None, params: dict | None = None):
    return OmegaConf.create({"hydra": {
        "mode": RunMode.MULTIRUN, "sweep": {"dir": str(sweep)}, "job": {"num": num},
        "runtime": {"output_dir": str(sweep / str(num))}, "overrides": {"task": task or []},
        "sweeper": {"_target_": "hydra._internal.core_plugins.basic_sweeper.BasicSweeper", "params": params or {}},
    }})  # fmt: skip


def test_the_job_count_is_the_product_of_the_swept_values(tmp_path: Path) -> None:
    assert sweep_size(_config(tmp_path, task=["algo=qmix,vdn", "seed=0,1,2", "env=map20"])) == 6
    assert sweep_size(_config(tmp_path, task=["algo=qmix,vdn"], params={"seed": "0,1,2,3,4"})) == 10
    other = _config(tmp_path)
    other.hydra.sweeper._target_ = "hydra_plugins.hydra_optuna_sweeper.optuna_sweeper.OptunaSweeper"
    assert sweep_size(other) is None  # another sweeper: the lines say only how many are done
    assert clock(59.6) == "1:00" and clock(3723) == "1:02:03"


def test_each_job_prints_the_progress_and_a_failed_one_keeps_its_row(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """Jobs report from their own process (a joblib or Ray launcher runs them elsewhere): each writes its
    row; the table is rewritten after every job, so a sweep stopped by a failure still has it."""
    sweep = tmp_path / "sweep"
    launcher = SweepProgress("mcrs-train")
    launcher.on_multirun_start(_config(sweep, task=["seed=0,1,2"]))
    scalars = sweep / "0" / "logs" / "scalars" / "eval"
    scalars.mkdir(parents=True)
    (scalars / "episode_reward.csv").write_text("0,1.5\n200,12.345\n")
    (scalars / "no_fly_violations.csv").write_text("0,3.0\n200,0.5\n")
    job = SweepProgress("mcrs-train")  # the job process's copy
    job.on_job_start(_config(sweep, 0))
    done = SimpleNamespace(status=JobStatus.COMPLETED, _return_value=12.345, overrides=["seed=0"])
    job.on_job_end(_config(sweep, 0), done)
    out = capsys.readouterr().out
    assert re.fullmatch(
        r"mcrs-train sweep: 1 of 3 done, elapsed [\d:]+, ETA [\d:]+; job 0 \(seed=0\): reward 12.35\n", out
    )
    job.on_job_start(_config(sweep, 1))
    failed = SimpleNamespace(
        status=JobStatus.FAILED, _return_value=RuntimeError("boom\nmore"), overrides=["seed=1"]
    )
    job.on_job_end(_config(sweep, 1), failed)
    assert "2 of 3 done (1 failed)" in capsys.readouterr().out
    table = (sweep / SUMMARY).read_text()
    assert re.search(r"\| 0 +\| seed=0 +\| 12\.35 +\| 0\.50 +\| [\d:]+ +\| done +\|", table), table
    assert re.search(r"\| 1 +\| seed=1 +\| - +\| - +\| [\d:]+ +\| failed: boom +\|", table), table
    assert sorted(p.name for p in (sweep / STATE_DIR).iterdir()) == [
        "job_00000.json",
        "job_00001.json",
        "start.json",
    ]
    single = OmegaConf.create({"hydra": {"mode": RunMode.RUN, "sweep": {"dir": str(tmp_path / "run")}}})
    job.on_job_end(single, done)  # not a sweep: nothing
    assert not (tmp_path / "run").exists() and capsys.readouterr().out == ""


@pytest.mark.slow
def test_a_training_sweep_prints_its_progress_and_ends_with_the_summary_table(tmp_path: Path) -> None:
    """Two tiny mcrs-train jobs on the basic launcher."""
    sweep = tmp_path / "sweep"
    command = [sys.executable, "-m", "mcrs.train", "-m", "algo=qmix", *TINY, "train.total_env_steps=40",
               "seed=0,1", f"hydra.sweep.dir={sweep}"]  # fmt: skip
    done = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=600,
                          env={**os.environ, "HYDRA_FULL_ERROR": "0"})  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    out = done.stdout
    assert re.search(
        r"^mcrs-train sweep: 1 of 2 done, elapsed [\d:]+, ETA [\d:]+; job 0 \(.*seed=0\): reward -?\d",
        out,
        re.M,
    ), out
    assert re.search(r"^mcrs-train sweep: 2 of 2 done, elapsed [\d:]+; job 1 ", out, re.M), out
    assert re.search(r"^mcrs-train sweep finished: 2 of 2 done, elapsed [\d:]+$", out, re.M), out
    table = (sweep / SUMMARY).read_text()
    assert table.split("\n\n", 1)[1] in out  # the table printed is the file's
    assert "every job: algo=qmix" in table
    header, _, *rows = [line for line in table.splitlines() if line.startswith("|")]
    assert [c.strip() for c in header.strip("|").split("|")] == [
        "job", "overrides", "episode reward", "no-fly violations", "wall time", "status"]  # fmt: skip
    assert [[c.strip() for c in r.strip("|").split("|")][1] for r in rows] == ["seed=0", "seed=1"]
    for row in rows:
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert all(re.fullmatch(r"-?\d+\.\d\d", c) for c in cells[2:4]), cells  # the final evaluation's
        assert cells[5] == "done"
