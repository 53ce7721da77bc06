"""A checkpoint written by a pre-release mcrs (before the callbacks: the memory under ``episodic``, EMC's
curiosity inside the learner's state) is refused in one line, by ``resume`` and by the tools that read
it; the weights files (which never had callbacks) keep loading. A saved config's legacy values stay."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from mcrs.env.config import from_mapping
from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.run import history
from mcrs.experiment.training.trainer import Experiment
from mcrs.policies.trained import TrainedPolicy
from mcrs_lab.analysis import horizon
from tests.train_helpers import compose_config

REFUSAL = (
    "was written by a pre-release mcrs (its memory and curiosity are not in 'callbacks'); "
    "it cannot be resumed: start a new run"
)


@pytest.fixture(scope="module")
def pre_release_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny QMIX run whose ``last.pt`` is rewritten in the pre-release layout."""
    run_dir = tmp_path_factory.mktemp("pre_release") / "run"
    Experiment(compose_config("train.total_env_steps=40"), run_dir).run()
    last = ckpt.checkpoint_path(run_dir)
    state = {k: v for k, v in ckpt.load(last).items() if k not in ("format", "version", "callbacks")}
    state["episodic"] = {"memory": {"keys": torch.zeros(3, 4)}, "embedding": {"w": torch.ones(2)}}
    state["learner"] = {**state["learner"], "curiosity": {"modules": {"w": torch.ones(1)}}}
    ckpt.save_atomic(state, last)
    return run_dir


@pytest.mark.parametrize("where", ["episodic", "curiosity"])
def test_either_mark_of_the_pre_release_layout_is_refused(where: str, tmp_path: Path) -> None:
    state = {"learner": {"agent": {}}, "counters": {"env_steps": 4}}
    if where == "episodic":
        state["episodic"] = {"memory": {}}
    else:
        state["learner"]["curiosity"] = {"modules": {}}
    with pytest.raises(ckpt.CheckpointError) as refused:
        ckpt.refuse_pre_release(state, tmp_path / "last.pt")
    assert str(refused.value) == f"{tmp_path / 'last.pt'} {REFUSAL}"
    today = {**state, "callbacks": {}}
    assert ckpt.refuse_pre_release(today, tmp_path / "last.pt") is today  # today's layout passes


def test_resume_refuses_a_pre_release_checkpoint_in_one_line(pre_release_run: Path) -> None:
    last = ckpt.checkpoint_path(pre_release_run)
    with pytest.raises(ckpt.CheckpointError) as refused:
        Experiment(compose_config("train.total_env_steps=40"), pre_release_run, resume=True)
    assert str(refused.value) == f"{last} {REFUSAL}"


def test_mcrs_train_resume_refuses_a_pre_release_checkpoint_without_a_traceback(
    pre_release_run: Path, tmp_path: Path
) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "mcrs.train", f"resume={pre_release_run}"],
        cwd=tmp_path,
        env={**os.environ, "HYDRA_FULL_ERROR": "0"},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode != 0
    assert "Traceback" not in done.stderr, done.stderr
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert lines == [f"mcrs-train: error: {ckpt.checkpoint_path(pre_release_run)} {REFUSAL}"], done.stderr


def test_a_tool_that_reads_it_says_the_same_line(pre_release_run: Path) -> None:
    with pytest.raises(SystemExit) as refused:
        horizon.main([str(pre_release_run)])
    assert str(refused.value).endswith(f"{ckpt.checkpoint_path(pre_release_run)} {REFUSAL}")


def test_the_weights_files_of_such_a_run_still_load(pre_release_run: Path) -> None:
    """``model_*.pt`` never had callbacks: what ``mcrs-eval`` loads is not refused."""
    weights = sorted(ckpt.checkpoint_path(pre_release_run).parent.glob("model_*.pt"))[-1]
    state = ckpt.load(weights)
    assert "callbacks" not in state and ckpt.refuse_pre_release(state, weights) is state
    policy = TrainedPolicy.from_checkpoint(weights, from_mapping(state["config"]["env"]))
    assert policy.agent is not None


def test_a_saved_config_loses_the_env_runtime_fields_only() -> None:
    saved = {"env": {"name": "map10", "width": 10, "num_envs": 32, "device": "cpu"}, "seed": 3}
    # ... and gains the fields it predates, at the values it was made under (mcrs.env.config).
    old = {
        "safety_rule": "near",
        "no_fly_view": "belief",
        "no_fly_prior": "unknown",
        "discovery_rule": "target",
    }
    assert history.current_config(saved) == {"env": {"name": "map10", "width": 10, **old}, "seed": 3}
    assert history.current_config({"seed": 3}) == {"seed": 3}


def test_fingerprints_name_classes_by_their_names_before_the_rooms() -> None:
    """Checkpoints written before mcrs/experiment/ had rooms name mcrs.experiment.algorithms.Algorithm; a
    fingerprint still does, so they resume (run/history.py). Classes elsewhere keep their own module."""
    from mcrs.experiment.run.history import class_path
    from mcrs.experiment.training.algorithms import Algorithm
    from mcrs.experiment.training.task import MCRSTask
    from mcrs.tasks import MatrixGameTask

    assert class_path(Algorithm) == "mcrs.experiment.algorithms.Algorithm"
    assert class_path(MCRSTask) == "mcrs.experiment.task.MCRSTask"
    assert class_path(MatrixGameTask) == "mcrs.tasks.matrix_game.MatrixGameTask"
