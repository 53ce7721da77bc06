"""Ctrl-C (SIGINT) and SIGTERM stop ``mcrs-train`` cleanly: a real process at a tiny size gets the signal
mid-run, prints one line and the resume command (no traceback, no leaked-semaphore warning), exits
128 + the signal, and leaves a checkpoint of the batch it was in; ``resume=`` then continues from exactly
that env step and ends where an uninterrupted run ends, with the same counters and weights."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.run.interrupt import RunInterrupted, StopSignals, TerminateAsInterrupt, Terminated
from tests.train_helpers import TINY

pytestmark = pytest.mark.slow

BATCH_STEPS = 40  # TINY: 4 envs x 10-step episodes per collector batch
MORE = 200  # env steps the resumed run trains after the interrupt


def _command(run_dir: Path, *overrides: str) -> list[str]:
    return [sys.executable, "-m", "mcrs.train", "algo=qmix", *TINY, *overrides, f"hydra.run.dir={run_dir}"]


def _run(command: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "HYDRA_FULL_ERROR": "0"}
    return subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)


def _interrupt(
    run_dir: Path, signum: int, cwd: Path, *extra: str, group: bool = False
) -> tuple[int, str, str]:
    """Start a run far too long to finish, signal it once it has trained a few batches (``group``: its
    whole process group, as a terminal's Ctrl-C does); its exit status and output."""
    env = {**os.environ, "HYDRA_FULL_ERROR": "0"}
    command = _command(
        run_dir, "train.total_env_steps=10000000", "train.checkpoint_interval=10000000", *extra
    )
    out, err = cwd / f"{run_dir.name}.out", cwd / f"{run_dir.name}.err"  # files: a full pipe stalls a run
    with open(out, "w") as stdout, open(err, "w") as stderr:
        process = subprocess.Popen(
            command, cwd=cwd, env=env, stdout=stdout, stderr=stderr, start_new_session=group
        )
        rows = run_dir / "logs" / "scalars" / "train" / "episodes.csv"  # a row per log_interval=40 steps
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and process.poll() is None:
            if rows.is_file() and len(rows.read_text().splitlines()) >= 3:
                break
            time.sleep(0.2)
        assert process.poll() is None, f"the run ended before the signal: {err.read_text()}"
        if group:
            os.killpg(process.pid, signum)
        else:
            process.send_signal(signum)
        code = process.wait(timeout=300)
    return code, out.read_text(), err.read_text()


def _state(run_dir: Path) -> dict:
    return ckpt.load(ckpt.checkpoint_path(run_dir))


@pytest.mark.parametrize(
    ("signum", "name", "code"), [(signal.SIGINT, "SIGINT", 130), (signal.SIGTERM, "SIGTERM", 143)]
)
def test_a_signal_saves_and_resume_continues_exactly(
    signum: int, name: str, code: int, tmp_path: Path
) -> None:
    stopped = tmp_path / "stopped"
    exit_code, out, err = _interrupt(stopped, signum, tmp_path)
    assert exit_code == code, (out, err)
    assert "Traceback" not in out + err and "leaked semaphore" not in out + err, err
    lines = [line for line in out.splitlines() if line.startswith("mcrs-train:")]
    assert len(lines) == 1 and lines[0].startswith(f"mcrs-train: {name}: stopped at env step "), out
    assert f"resume with: mcrs-train resume={stopped}" in out

    steps = int(lines[0].split("env step ")[1].split(",")[0])
    state = _state(stopped)
    assert state["counters"]["env_steps"] == steps > 0 and steps % BATCH_STEPS == 0
    assert ckpt.weights_path(stopped, steps).is_file()
    assert not list((stopped / "checkpoints").glob("*.tmp*"))  # nothing half-written

    total = steps + MORE
    resumed = _run(_command(stopped, f"resume={stopped}", f"train.total_env_steps={total}"), tmp_path)
    assert resumed.returncode == 0, resumed.stderr
    assert "resuming qmix on map10" in resumed.stdout

    straight = tmp_path / "straight"
    done = _run(
        _command(straight, f"train.total_env_steps={total}", "train.checkpoint_interval=10000000"), tmp_path
    )
    assert done.returncode == 0, done.stderr
    a, b = _state(stopped), _state(straight)
    assert a["counters"] == b["counters"] and a["counters"]["env_steps"] == total
    for name_, value in b["learner"]["agent"].items():
        assert torch.equal(value, a["learner"]["agent"][name_]), name_
    for name_, value in b["learner"]["mixer"].items():
        assert torch.equal(value, a["learner"]["mixer"][name_]), name_


def test_ctrl_c_to_the_process_group_of_a_multiprocess_run(tmp_path: Path) -> None:
    """A terminal's Ctrl-C reaches the collector's worker processes too: they ignore it, the trainer ends
    the batch, saves and exits; a resume finishes the run."""
    stopped = tmp_path / "multi"
    workers = ("train.collector=multiprocess", "train.collector_workers=2")
    exit_code, out, err = _interrupt(stopped, signal.SIGINT, tmp_path, *workers, group=True)
    assert exit_code == 130, (out, err)
    assert "Traceback" not in out + err and "leaked semaphore" not in out + err, err
    (line,) = [line for line in out.splitlines() if line.startswith("mcrs-train:")]
    steps = int(line.split("env step ")[1].split(",")[0])
    assert _state(stopped)["counters"]["env_steps"] == steps > 0
    total = steps + 2 * BATCH_STEPS
    resumed = _run(_command(stopped, f"resume={stopped}", f"train.total_env_steps={total}"), tmp_path)
    assert resumed.returncode == 0, resumed.stderr
    assert _state(stopped)["counters"]["env_steps"] == total


def test_stop_signals_record_the_first_signal_and_restore_the_handlers() -> None:
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    with StopSignals() as stop:
        assert not stop.requested
        os.kill(os.getpid(), signal.SIGTERM)
        os.kill(os.getpid(), signal.SIGINT)  # a second signal (Ctrl-C during the save) changes nothing
        time.sleep(0.05)
        assert stop.requested and stop.signum == signal.SIGTERM
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before


def test_run_interrupted_is_a_keyboard_interrupt_with_the_shell_exit_status(tmp_path: Path) -> None:
    error = RunInterrupted(signal.SIGINT, tmp_path, 120, tmp_path / "checkpoints" / "last.pt")
    assert isinstance(error, KeyboardInterrupt)
    assert error.exit_code == 130 and error.signal_name == "SIGINT"
    assert f"resume with: mcrs-train resume={tmp_path}" in str(error)
    assert RunInterrupted(signal.SIGTERM, tmp_path, 0, tmp_path).exit_code == 143


def test_sigterm_while_the_run_is_built_is_one_line_exit_143_and_no_directory(
    tmp_path: Path, monkeypatch, capsys
) -> None:
    """Before the training loop takes the signals over, SIGTERM used to kill ``mcrs-train`` without a word
    and leave Hydra's directory behind; now it stops as Ctrl-C does there, and the handler is restored."""
    import mcrs.train as train

    def terminated_while_building(*args) -> dict:
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)  # the handler raises in here
        raise AssertionError("SIGTERM did not stop the run")

    before = signal.getsignal(signal.SIGTERM)
    run_dir = tmp_path / "run"
    monkeypatch.setattr(train, "run", terminated_while_building)
    monkeypatch.setattr(sys, "argv", ["mcrs-train", "algo=qmix", *TINY, f"hydra.run.dir={run_dir}"])
    with pytest.raises(SystemExit) as stop:
        train.main()
    assert stop.value.code == 143
    assert (
        "mcrs-train: SIGTERM: interrupted before training started: nothing to save" in capsys.readouterr().out
    )
    assert not run_dir.exists()
    assert signal.getsignal(signal.SIGTERM) == before


def test_terminate_as_interrupt_raises_a_keyboard_interrupt_with_status_143() -> None:
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Terminated) as stop, TerminateAsInterrupt():
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)
    assert isinstance(stop.value, KeyboardInterrupt) and stop.value.exit_code == 143
    assert signal.getsignal(signal.SIGTERM) == before


def test_ctrl_c_then_resume_leaves_one_run_directory_whose_log_holds_both_sessions(tmp_path: Path) -> None:
    """As a user does it: ``mcrs-train`` (Hydra's own directory name), Ctrl-C, ``mcrs-train resume=<dir>``:
    the resumed session works in the run's directory (no second one appears) and appends to its train.log."""
    env = {**os.environ, "HYDRA_FULL_ERROR": "0"}
    base = [sys.executable, "-m", "mcrs.train", "algo=qmix", *TINY, "train.checkpoint_interval=10000000"]
    with open(tmp_path / "first.out", "w") as out:
        process = subprocess.Popen([*base, "train.total_env_steps=10000000"], cwd=tmp_path, env=env,
                                   stdout=out, stderr=subprocess.STDOUT)  # fmt: skip
        deadline = time.monotonic() + 300
        while process.poll() is None and time.monotonic() < deadline:
            rows = list((tmp_path / "outputs").glob("map10/qmix/*/logs/scalars/train/episodes.csv"))
            if rows and len(rows[0].read_text().splitlines()) >= 3:
                break
            time.sleep(0.2)
        assert process.poll() is None, (tmp_path / "first.out").read_text()
        process.send_signal(signal.SIGINT)
        assert process.wait(timeout=300) == 130
    (run_dir,) = (tmp_path / "outputs" / "map10" / "qmix").iterdir()
    steps = _state(run_dir)["counters"]["env_steps"]

    resumed = _run([*base, f"resume={run_dir}", f"train.total_env_steps={steps + 2 * BATCH_STEPS}"], tmp_path)
    assert resumed.returncode == 0, resumed.stderr
    assert [p.relative_to(tmp_path / "outputs") for p in (tmp_path / "outputs").glob("*/*/*")] == [
        run_dir.relative_to(tmp_path / "outputs")
    ]  # exactly one run directory, no stray one named after the default algorithm
    assert _state(run_dir)["counters"]["env_steps"] == steps + 2 * BATCH_STEPS
    log = (run_dir / "train.log").read_text()
    first, stop, second = (
        log.index("training qmix"),
        log.index("SIGINT: stopped at env step"),
        log.index("resuming qmix"),
    )
    assert first < stop < second, log  # one log: the first session, where it stopped, the resumed one
    assert f"evaluation at env step {steps + 2 * BATCH_STEPS}" in log[second:]
    assert (run_dir / ".hydra" / "overrides.yaml").is_file()  # the first session's Hydra files are kept
    (session,) = (run_dir / ".hydra").glob("resumed_*")
    assert f"resume={run_dir}" in (session / "overrides.yaml").read_text()


@pytest.mark.parametrize("when", ["loading", "job"])
def test_ctrl_c_before_training_is_one_line_and_exit_130(tmp_path: Path, when: str) -> None:
    """Ctrl-C while the modules load (``loading``: once Hydra's first module has loaded, which Python's
    ``-X importtime`` tells) or once Hydra has made the run directory (``job``: composing, the config
    checks, torch loading): one line, exit 130, no traceback (issue 33). Where exactly the signal lands
    does not matter: every place before training says the same."""
    run_dir = tmp_path / "run"
    env = {**os.environ, "HYDRA_FULL_ERROR": "0"}
    command = _command(run_dir, "train.total_env_steps=10000000")
    process = subprocess.Popen(
        [command[0], "-X", "importtime", *command[1:]], cwd=tmp_path, env=env,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        # as from a terminal: a child inherits an ignored SIGINT (a background shell, a test worker that
        # ignored it), and Python then keeps ignoring it, as mcrs-train does
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip
    try:
        assert process.stderr is not None
        seen = []
        for line in process.stderr:  # one line per module loaded, as its import ends
            seen.append(line)
            if "| hydra" in line:  # imported after mcrs.train's first lines: its handler is in place
                break
        if when == "job":
            deadline = time.monotonic() + 120
            while not run_dir.exists():
                assert process.poll() is None and time.monotonic() < deadline, process.communicate()
                time.sleep(0.01)
        process.send_signal(signal.SIGINT)
        out, err = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    assert process.returncode == 130, (out, err[-3000:])
    assert "Traceback" not in out + err, err[-3000:]
    lines = [line for line in (out + err).splitlines() if line.startswith("mcrs-train:")]
    assert lines == ["mcrs-train: SIGINT: interrupted before training started: nothing to save"], (out, err)
    assert not ckpt.checkpoint_path(run_dir).exists()
    if when == "loading":
        assert not run_dir.exists()  # nothing was written
