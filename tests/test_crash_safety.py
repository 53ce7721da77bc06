"""Crash safety: a training process killed with SIGKILL at a random moment resumes from its last checkpoint.

The run writes a checkpoint every collector batch; it is killed (no chance to clean up) at a seeded
random moment after its first checkpoint, then ``mcrs-train resume=<run>`` finishes it. Checked: the
resumed run exits 0 and reaches ``total_env_steps``; every file under ``checkpoints/`` loads (none is
half-written) and no temporary is left; the resumed run starts exactly from the last checkpoint, so at
most one checkpoint interval of work is lost. (N straight == N/2 + resume is tested in test_training.py
and test_memory_training.py.)
"""

from __future__ import annotations

import csv
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mcrs.experiment.run import checkpoint as ckpt
from tests.train_helpers import TINY, TINY_MEMORY

pytestmark = pytest.mark.slow

BATCH_STEPS = 40  # TINY: 4 envs x 10-step episodes per collector batch
INTERVAL = BATCH_STEPS  # a checkpoint after every batch
TOTAL = 4000


def _command(run_dir: Path, *overrides: str) -> list[str]:
    return [sys.executable, "-m", "mcrs.train", *overrides, f"hydra.run.dir={run_dir}"]


def _train_overrides(algo: str) -> list[str]:
    extra = TINY_MEMORY if algo == "cnn_semu" else []
    return [
        f"algo={algo}",
        *TINY,
        *extra,
        f"train.total_env_steps={TOTAL}",
        f"train.checkpoint_interval={INTERVAL}",
        "train.eval_interval=2000",
        f"logger.log_interval={BATCH_STEPS}",
    ]


def _logged_steps(run_dir: Path, name: str = "train/episodes") -> list[int]:
    """The env steps of the rows of a CSV log (train/: one row per batch; flushed at every row)."""
    path = run_dir / "logs" / "scalars" / f"{name}.csv"
    if not path.is_file():
        return []
    with open(path) as f:
        return [int(float(row[0])) for row in csv.reader(f) if row]


def _kill_at_random_moment(run_dir: Path, algo: str, seed: int, cwd: Path) -> None:
    env = {**os.environ, "HYDRA_FULL_ERROR": "0"}
    log = cwd / "killed_run.log"  # a file, not a pipe: a full pipe would stall the run
    with open(log, "w") as stderr:
        proc = subprocess.Popen(
            _command(run_dir, *_train_overrides(algo)), cwd=cwd, env=env, stdout=stderr, stderr=stderr
        )
        last = ckpt.checkpoint_path(run_dir)
        deadline = time.monotonic() + 240
        while not last.is_file():
            assert proc.poll() is None, (
                f"the run ended before its first checkpoint: {log.read_text()[-3000:]}"
            )
            assert time.monotonic() < deadline, "no checkpoint within 240 s"
            time.sleep(0.02)
        time.sleep(random.Random(seed).uniform(0.0, 2.0))
        assert proc.poll() is None, "the run finished before it could be killed: raise TOTAL"
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL


@pytest.mark.parametrize(("algo", "seed"), [("qmix", 0), ("qmix", 1), ("cnn_semu", 2)])
def test_sigkill_at_a_random_moment_then_resume(algo: str, seed: int, tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    _kill_at_random_moment(run_dir, algo, seed, tmp_path)

    # What the kill left: last.pt is whole and holds the progress of the last checkpoint.
    state = ckpt.load(ckpt.checkpoint_path(run_dir))
    resumed_from = state["counters"]["env_steps"]
    steps_at_kill = max(_logged_steps(run_dir))
    assert 0 < resumed_from <= steps_at_kill
    # A batch may have been collected (and logged) after the last checkpoint but not saved: lost work.
    assert steps_at_kill - resumed_from <= INTERVAL, (steps_at_kill, resumed_from)
    if algo == "cnn_semu":
        assert "memory" in state["callbacks"] and state["callbacks"]["memory"]["memory"]
    # A save cut by the kill leaves a temporary: planted here too, so the clean-up is always exercised.
    (run_dir / "checkpoints" / ".last.pt.killed.tmp").write_bytes(b"half a checkpoint")

    done = subprocess.run(
        _command(tmp_path / "unused", f"resume={run_dir}", "logger.progress_bar=false"),
        cwd=tmp_path,
        env={**os.environ, "HYDRA_FULL_ERROR": "0"},
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert f"resuming {algo} on map10: {run_dir}" in done.stdout

    final = ckpt.load(ckpt.checkpoint_path(run_dir))
    assert final["counters"]["env_steps"] == TOTAL
    assert final["counters"]["episodes"] == TOTAL // 10
    # The rows logged after the checkpoint (lost work) were dropped and logged again once: every batch
    # and every evaluation has exactly one row, and the resumed session went on from the checkpoint.
    assert _logged_steps(run_dir) == list(range(BATCH_STEPS, TOTAL + 1, BATCH_STEPS))
    assert _logged_steps(run_dir, "eval/episode_reward") == [0, 2000, 4000]
    files = sorted((run_dir / "checkpoints").iterdir())
    assert not [f.name for f in files if f.name.startswith(".")], "temporaries left behind"
    for path in files:
        ckpt.load(path)  # raises CheckpointError on a half-written file
    assert (run_dir / "checkpoints" / f"model_{TOTAL:09d}.pt") in files
