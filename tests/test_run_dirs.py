"""A run directory belongs to one run (issue 14).

Runs started together get their own directories and complete logs; one process writes a run (a second
writer and a resume of a live run are refused naming the holder's PID); a checkpoint from another run is
refused naming the first field that differs; a fresh run refuses a non-empty directory unless told to
overwrite; a full disk, an unwritable directory and an unreadable config are one line and keep the last
checkpoint; a resumed run logs no row twice and writes its checkpoints where a straight run does.
"""

from __future__ import annotations

import csv
import errno
import os
import resource
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from mcrs.experiment.config import ConfigError
from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.run.rundir import LOCK, RunDirError, RunLock
from mcrs.experiment.training.trainer import Experiment
from mcrs.train import resume_config
from tests.train_helpers import TINY, TINY_MEMORY, compose_config, start_train

pytestmark = pytest.mark.slow

BATCH = 40  # TINY: 4 envs x 10 steps per collector batch


def _finish(proc: subprocess.Popen, timeout: float = 300) -> tuple[int, str, str]:
    out, err = proc.communicate(timeout=timeout)
    return proc.returncode, out, err


def _assert_one_line_error(rc: int, stderr: str, *expected: str) -> str:
    """A non-zero exit with one ``mcrs-train: error:`` line and no traceback; returns the line."""
    assert rc != 0
    assert "Traceback" not in stderr, stderr
    errors = [line for line in stderr.splitlines() if line.startswith("mcrs-train: error:")]
    assert len(errors) == 1, stderr
    for text in expected:
        assert text in errors[0], errors[0]
    return errors[0]


def _rows(run_dir: Path, name: str = "train/episodes") -> list[list[str]]:
    with open(run_dir / "logs" / "scalars" / f"{name}.csv") as f:
        return [row for row in csv.reader(f) if row]


def _csv_logs(run_dir: Path) -> dict[str, list[list[str]]]:
    """Every CSV log but the wall-clock timings (``time/``), by name."""
    root = run_dir / "logs" / "scalars"
    return {
        p.relative_to(root).as_posix(): _rows(run_dir, p.relative_to(root).with_suffix("").as_posix())
        for p in sorted(root.rglob("*.csv"))
        if not p.relative_to(root).as_posix().startswith("time/")
    }


# ------------------------------------------------------------------------------ unique directories
def test_runs_started_together_get_their_own_directories_and_complete_logs(tmp_path: Path) -> None:
    """Two plain runs and two multiruns with the same config, started at once: four run directories."""
    args = [
        "algo=qmix",
        *TINY,
        "train.total_env_steps=80",
        "train.checkpoint_interval=40",
        "train.eval_interval=80",
    ]
    procs = [start_train(*args, cwd=tmp_path) for _ in range(2)] + [
        start_train("-m", *args, cwd=tmp_path) for _ in range(2)
    ]
    for proc in procs:
        rc, _, err = _finish(proc)
        assert rc == 0, err[-3000:]
    runs = sorted((tmp_path / "outputs" / "map10" / "qmix").iterdir())
    sweeps = sorted((tmp_path / "outputs" / "multirun").glob("*/0_map10_qmix_seed0"))
    assert len(runs) == 2 and len(sweeps) == 2, (runs, sweeps)
    for run_dir in runs + sweeps:
        assert [int(row[0]) for row in _rows(run_dir)] == [40, 80]  # each run's own rows, once
        assert [int(float(row[0])) for row in _rows(run_dir, "eval/episode_reward")] == [0, 80]
        assert ckpt.load(ckpt.checkpoint_path(run_dir))["counters"]["env_steps"] == 80


# ------------------------------------------------------------------------------ one writer
def test_a_second_writer_and_a_resume_of_a_live_run_are_refused_naming_the_pid(tmp_path: Path) -> None:
    run_dir = tmp_path / "live"
    live = subprocess.Popen(  # output to /dev/null: a full pipe would stall it
        [
            sys.executable,
            "-m",
            "mcrs.train",
            "algo=qmix",
            *TINY,
            "train.total_env_steps=100000",
            f"hydra.run.dir={run_dir}",
        ],
        cwd=tmp_path,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 120
        while not ckpt.checkpoint_path(run_dir).is_file():
            assert live.poll() is None and time.monotonic() < deadline, "the live run did not checkpoint"
            time.sleep(0.05)
        hydra_files = _hashes(run_dir / ".hydra")
        resume = start_train(f"resume={run_dir}", cwd=tmp_path)  # both at once: they only wait for imports
        second = start_train("algo=qmix", *TINY, "overwrite=true", f"hydra.run.dir={run_dir}", cwd=tmp_path)
        rc, _, err = _finish(resume)
        _assert_one_line_error(rc, err, f"run directory {run_dir} is in use by process {live.pid}")
        rc, _, err = _finish(second)
        _assert_one_line_error(rc, err, f"is in use by process {live.pid}")
        assert live.poll() is None, "the live run was disturbed"
        assert _hashes(run_dir / ".hydra") == hydra_files  # the live run's Hydra files, untouched
    finally:
        live.send_signal(signal.SIGKILL)
        live.wait(timeout=30)
    # The kernel drops the lock of a killed process: the run can be resumed at once.
    RunLock(run_dir).release()


def _hashes(directory: Path) -> dict[str, str]:
    """Every file under ``directory`` (hidden ones too) and the SHA-256 of its bytes."""
    import hashlib

    return {
        p.relative_to(directory).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(directory.rglob("*"))
        if p.is_file()
    }


def test_a_refused_command_into_an_existing_run_leaves_every_file_of_it_as_it_was(tmp_path: Path) -> None:
    """Hydra writes ``.hydra/`` and appends to the log when the job starts: a fresh run refused for the
    directory of an existing run must be refused before that (issue 33)."""
    run_dir = tmp_path / "run"
    args = ["algo=qmix", *TINY, "train.total_env_steps=40", f"hydra.run.dir={run_dir}"]
    rc, _, err = _finish(start_train(*args, cwd=tmp_path))
    assert rc == 0, err[-3000:]
    before = _hashes(run_dir)
    assert {".hydra/config.yaml", ".hydra/overrides.yaml", "train.log", "config.yaml"} <= set(before)

    rc, _, err = _finish(start_train(*args, "seed=5", cwd=tmp_path))
    _assert_one_line_error(rc, err, f"run directory {run_dir} is not empty", "overwrite=true")
    assert _hashes(run_dir) == before

    (run_dir / "notes.txt").write_text("mine")
    before = _hashes(run_dir)
    rc, _, err = _finish(start_train(*args, "seed=5", "overwrite=true", cwd=tmp_path))
    _assert_one_line_error(rc, err, "holds files that no run wrote (notes.txt)")
    assert _hashes(run_dir) == before

    (run_dir / "notes.txt").unlink()  # overwrite=true may replace the run, but not for a refused config
    before = _hashes(run_dir)
    rc, _, err = _finish(start_train(*args, "overwrite=true", "train.lr=-1", cwd=tmp_path))
    _assert_one_line_error(rc, err, "invalid config: train.lr=-1")
    assert _hashes(run_dir) == before


def test_the_lock_is_held_while_the_trainer_lives_and_released_by_train(tmp_path: Path) -> None:
    trainer = Experiment(compose_config("train.total_env_steps=40"), tmp_path / "run")
    with pytest.raises(RunDirError, match=f"in use by process {os.getpid()}"):
        Experiment(compose_config("train.total_env_steps=40"), tmp_path / "run")
    trainer.run()
    assert (tmp_path / "run" / LOCK).is_file()
    RunLock(tmp_path / "run").release()  # free again


# ------------------------------------------------------------------------------ foreign checkpoints
def _resume(run_dir: Path, *extra: str) -> Experiment:
    overrides = [f"resume={run_dir}", *extra]
    cfg, run_dir = resume_config(compose_config(*overrides), overrides)
    return Experiment(cfg, run_dir, resume=True)


@pytest.fixture(scope="module")
def qmix_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    run_dir = tmp_path_factory.mktemp("qmix") / "run"
    Experiment(compose_config("train.total_env_steps=40"), run_dir).run()
    return run_dir


@pytest.mark.parametrize(
    ("other", "difference"),
    [
        (["algo=cnn_semu", *TINY_MEMORY], "algo.name: 'cnn_semu' in the checkpoint, 'qmix' in this run"),
        (["algo=vdn"], "algo.name: 'vdn' in the checkpoint, 'qmix' in this run"),
        (["env.width=8", "env.height=8"], "env.width: 8 in the checkpoint, 10 in this run"),
        (["model.hidden_dim=8"], "model.hidden_dim: 8 in the checkpoint, 16 in this run"),
        (["seed=1"], "seed: 1 in the checkpoint, 0 in this run"),
    ],
    ids=["cnn_semu", "vdn", "map_shape", "network", "seed"],
)
def test_a_foreign_checkpoint_is_refused_naming_the_first_difference(
    other: list[str], difference: str, qmix_run: Path, tmp_path: Path
) -> None:
    foreign = tmp_path / "foreign"
    Experiment(compose_config("train.total_env_steps=40", *other), foreign).run()
    run_dir = tmp_path / "run"
    shutil.copytree(qmix_run, run_dir)
    shutil.copy(ckpt.checkpoint_path(foreign), ckpt.checkpoint_path(run_dir))
    with pytest.raises(ckpt.CheckpointError, match="does not belong to this run") as info:
        _resume(run_dir)
    assert str(info.value).endswith(difference) and "\n" not in str(info.value)
    # A checkpoint written before fingerprints is judged by the config and weights it holds.
    state = torch.load(ckpt.checkpoint_path(run_dir), weights_only=True)
    del state["fingerprint"], state["checksum"]  # neither existed then
    torch.save(state, ckpt.checkpoint_path(run_dir))
    with pytest.raises(ckpt.CheckpointError, match="does not belong to this run") as info:
        _resume(run_dir)
    assert str(info.value).endswith(difference)


def test_the_networks_are_part_of_the_fingerprint(qmix_run: Path, tmp_path: Path) -> None:
    """Same config, other network shapes (another version of the code): refused before loading."""
    run_dir = tmp_path / "run"
    shutil.copytree(qmix_run, run_dir)
    state = torch.load(ckpt.checkpoint_path(run_dir), weights_only=True)
    name = next(k for k in state["fingerprint"] if k.startswith("networks.mixer."))
    state["fingerprint"][name] = [1, 2, 3]
    whole = {k: v for k, v in state.items() if k not in ("format", "version", "checksum")}
    ckpt.save_atomic(whole, ckpt.checkpoint_path(run_dir))  # a whole file, its checksum its own
    with pytest.raises(ckpt.CheckpointError, match=f"{name}: \\[1, 2, 3\\] in the checkpoint"):
        _resume(run_dir)
    _resume(qmix_run).close()  # its own checkpoint is accepted


def test_first_difference_skips_schema_changes_but_not_network_changes() -> None:
    from mcrs.experiment.run.rundir import first_difference

    run = {"format.version": 1, "algo.name": "qmix", "algo.new_field": 3, "networks.agent.w": [4, 2]}
    assert (
        first_difference({"format.version": 1, "algo.name": "qmix", "networks.agent.w": [4, 2]}, run) is None
    )
    assert (
        first_difference({"algo.name": "qmix", "algo.old_field": 1, "networks.agent.w": [4, 2]}, run) is None
    )
    assert (
        first_difference({"algo.name": "qmix"}, run)
        == "networks.agent.w: '<missing>' in the checkpoint, [4, 2] in this run"
    )
    assert first_difference({"algo.name": "vdn", "networks.agent.w": [4, 2]}, run).startswith(
        "algo.name: 'vdn'"
    )


def test_cli_refuses_a_foreign_checkpoint_in_one_line(qmix_run: Path, tmp_path: Path) -> None:
    foreign = tmp_path / "foreign"
    Experiment(compose_config("algo=cnn_semu", *TINY_MEMORY, "train.total_env_steps=40"), foreign).run()
    run_dir = tmp_path / "run"
    shutil.copytree(qmix_run, run_dir)
    shutil.copy(ckpt.checkpoint_path(foreign), ckpt.checkpoint_path(run_dir))
    before = _csv_logs(run_dir)
    rc, _, err = _finish(start_train(f"resume={run_dir}", cwd=tmp_path))
    _assert_one_line_error(rc, err, "does not belong to this run: algo.name: 'cnn_semu' in the checkpoint")
    assert _csv_logs(run_dir) == before  # nothing was trained on from the foreign state


# ------------------------------------------------------------------------------ logs after a resume
def test_a_resumed_run_logs_every_row_once_and_checkpoints_where_a_straight_run_does(tmp_path: Path) -> None:
    """Killed after logging step 120 but before its checkpoint (last.pt at 80): the resumed run's logs and
    checkpoints are the straight run's, row for row (wall-clock timings aside)."""
    common = ["train.checkpoint_interval=80", "train.eval_interval=40"]
    straight = tmp_path / "straight"
    Experiment(compose_config("train.total_env_steps=200", *common), straight).run()

    run_dir = tmp_path / "run"
    Experiment(compose_config("train.total_env_steps=80", *common), run_dir).run()
    at_80 = tmp_path / "checkpoints_at_80"  # last.pt and the replay's block files it names
    shutil.copytree(run_dir / "checkpoints", at_80)
    _resume(run_dir, "train.total_env_steps=120").run()  # logs rows at 120 ...
    shutil.rmtree(run_dir / "checkpoints")  # ... then dies before checkpointing them
    shutil.copytree(at_80, run_dir / "checkpoints")
    assert [int(r[0]) for r in _rows(run_dir)] == [40, 80, 120]

    _resume(run_dir, "train.total_env_steps=200").run()
    assert _csv_logs(run_dir) == _csv_logs(straight)
    assert [int(r[0]) for r in _rows(run_dir)] == [40, 80, 120, 160, 200]
    assert [int(float(r[0])) for r in _rows(run_dir, "eval/episode_reward")] == [0, 40, 80, 120, 160, 200]

    def checkpoints(run: Path) -> list[str]:  # the replay's block files are named by save generation
        return sorted(p.name for p in (run / "checkpoints").iterdir() if not p.name.startswith("replay_"))

    names = checkpoints(straight)
    assert checkpoints(run_dir) == names  # no extra checkpoint
    assert names == ["last.pt", "model_000000080.pt", "model_000000160.pt", "model_000000200.pt"]


# ------------------------------------------------------------------------------ fresh runs
def test_a_fresh_run_refuses_a_non_empty_directory_unless_told_to_overwrite(tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    Experiment(compose_config("train.total_env_steps=80", "train.checkpoint_interval=40"), run_dir).run()
    assert (run_dir / "checkpoints" / "model_000000040.pt").is_file()
    with pytest.raises(
        RunDirError, match=r"is not empty \(checkpoints, config.yaml, logs\).*overwrite=true.*resume=True"
    ):
        Experiment(compose_config("train.total_env_steps=40"), run_dir)
    assert ckpt.load(ckpt.checkpoint_path(run_dir))["counters"]["env_steps"] == 80  # untouched

    Experiment(compose_config("train.total_env_steps=40", "overwrite=true", "seed=3"), run_dir).run()
    kept = sorted(p.name for p in (run_dir / "checkpoints").iterdir())
    assert kept == ["last.pt", "model_000000040.pt", "replay_00000_000001.pt"]  # only the new run's files
    assert [int(r[0]) for r in _rows(run_dir)] == [40]  # the old run's rows are gone, not mixed
    assert ckpt.load(ckpt.checkpoint_path(run_dir))["config"]["seed"] == 3

    (run_dir / "notes.txt").write_text("mine")  # overwrite replaces a run, never other files
    with pytest.raises(RunDirError, match=r"holds files that no run wrote \(notes.txt\)"):
        Experiment(compose_config("train.total_env_steps=40", "overwrite=true"), run_dir)
    assert (run_dir / "notes.txt").read_text() == "mine" and ckpt.checkpoint_path(run_dir).is_file()


# ------------------------------------------------------------------------------ I/O failures
def test_a_full_disk_stops_the_run_in_one_line_and_keeps_the_last_checkpoint(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    run_dir = tmp_path / "run"
    trainer = Experiment(compose_config("train.total_env_steps=200", "train.checkpoint_interval=40"), run_dir)
    saves = {"last": 0, "full": False}
    real_save = ckpt.save_atomic

    def counting_save(payload, path):
        is_last = Path(path).name == ckpt.LAST
        saves["last"] += is_last
        saves["full"] = saves["full"] or (is_last and saves["last"] >= 3)
        return real_save(payload, path)

    real_write = ckpt._Writer.write

    def write(self, data: bytes) -> int:
        if saves["full"]:  # from the third last.pt on (its replay blocks are written): the disk is full
            real_write(self, data[: len(data) // 2])
            self.error = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            raise self.error
        return real_write(self, data)

    monkeypatch.setattr(ckpt, "save_atomic", counting_save)
    monkeypatch.setattr(ckpt._Writer, "write", write)
    with pytest.raises(RunDirError) as info:
        trainer.run()
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(
        f"cannot write checkpoint {ckpt.checkpoint_path(run_dir)}: No space left on device"
    )
    assert f"the last checkpoint {ckpt.checkpoint_path(run_dir)} is intact" in message
    assert message.endswith(f"resume={run_dir}") and "no checkpoint had been written" not in message
    assert ckpt.load(ckpt.checkpoint_path(run_dir))["counters"]["env_steps"] == 80
    assert not [p.name for p in (run_dir / "checkpoints").iterdir() if p.name.startswith(".")]
    monkeypatch.undo()
    _resume(run_dir, "train.total_env_steps=120").run()  # the lock was released; the run goes on


def test_cli_file_too_large_is_one_line_and_the_last_checkpoint_is_intact(tmp_path: Path) -> None:
    """A real write error from the OS (RLIMIT_FSIZE: files above 400 kB cannot be written), no mock."""

    def limit() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write fails with EFBIG instead of a signal
        resource.setrlimit(resource.RLIMIT_FSIZE, (400_000, 400_000))

    run_dir = tmp_path / "run"
    args = [
        "algo=qmix",
        *TINY,
        "train.total_env_steps=400",
        "train.checkpoint_interval=40",
        "train.replay_episodes=200",
    ]
    rc, _, err = _finish(start_train(*args, f"hydra.run.dir={run_dir}", cwd=tmp_path, preexec_fn=limit))
    _assert_one_line_error(rc, err, "cannot write checkpoint", "File too large", "is intact")
    steps = ckpt.load(ckpt.checkpoint_path(run_dir))["counters"]["env_steps"]
    assert 40 <= steps < 400
    assert not [p.name for p in (run_dir / "checkpoints").iterdir() if p.name.startswith(".")]


def test_an_unwritable_run_directory_is_one_line(tmp_path: Path) -> None:
    (tmp_path / "a_file").write_text("")
    rc, _, err = _finish(start_train(*TINY, f"hydra.run.dir={tmp_path / 'a_file' / 'run'}", cwd=tmp_path))
    _assert_one_line_error(
        rc, err, f"cannot write the run directory {tmp_path / 'a_file' / 'run'}: Not a directory"
    )


@pytest.mark.parametrize(
    ("content", "reason"),
    [
        (b"seed: [1, 2\n", "is not a valid config"),
        (b"\xff\xfe\x00binary", "is not a valid config"),
        (b"seed: 0\nalgo:\n  lrr: 1\n", "does not fit this mcrs's config: Key 'lrr' not in 'AlgoConfig'"),
        (
            b"seed: !!python/object/apply:os.system ['touch pwned']\n",
            "is not plain YAML data .*python/object",
        ),
    ],
    ids=["malformed", "binary", "unknown_key", "python_tag"],
)
def test_a_bad_run_config_is_refused_in_one_line(content: bytes, reason: str, qmix_run: Path,
                                                 tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:  # fmt: skip
    monkeypatch.chdir(tmp_path)
    run_dir = tmp_path / "run"
    shutil.copytree(qmix_run, run_dir)
    (run_dir / "config.yaml").write_bytes(content)
    overrides = [f"resume={run_dir}"]
    with pytest.raises(ConfigError, match=reason) as info:
        resume_config(compose_config(*overrides), overrides)
    assert "\n" not in str(info.value) and str(run_dir / "config.yaml") in str(info.value)
    assert not (tmp_path / "pwned").exists()


def test_cli_bad_run_config_is_one_line(qmix_run: Path, tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    shutil.copytree(qmix_run, run_dir)
    (run_dir / "config.yaml").write_text("seed: 0\nalgo:\n  lrr: 1\n")
    rc, _, err = _finish(start_train(f"resume={run_dir}", cwd=tmp_path))
    _assert_one_line_error(rc, err, "does not fit this mcrs's config")


def test_a_log_write_on_a_full_disk_says_nothing_after_its_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A CSV log the disk refuses (/dev/full: every flush is ENOSPC) stops the run in one line; its file's
    unwritten buffer used to fail again when the logger was collected (``Exception ignored in
    CSVExperiment.__del__``). The run closes its log files, so nothing is left to fail."""
    import gc

    ignored: list[object] = []
    monkeypatch.setattr(sys, "unraisablehook", ignored.append)
    run_dir = tmp_path / "run"
    trainer = Experiment(compose_config("train.total_env_steps=80", "train.checkpoint_interval=40"), run_dir)
    experiment = trainer.logger.experiment
    path = os.path.join(experiment.log_dir, "scalars", "train", "epsilon.csv")
    handle = experiment.files[path] = open("/dev/full", "a+")  # noqa: SIM115 (the logger owns it)
    with pytest.raises(RunDirError, match="No space left on device") as info:
        trainer.run()
    assert "\n" not in str(info.value)
    assert handle.closed and experiment.files == {}
    del trainer, experiment, handle, info
    gc.collect()
    assert ignored == []
