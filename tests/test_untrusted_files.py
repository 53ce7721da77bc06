"""Untrusted files: checkpoints and configs never run code, bad files are refused in one line, logs stay offline.

tests/test_training.py already checks that a 1000-byte prefix of last.pt, a foreign dict and a pickled
callable are refused by ``checkpoint.load``; here the callable is shown *not to run*, more kinds of bad
file are tried, and ``mcrs-train resume=`` is shown to refuse each with one ``mcrs-train: error:`` line.
"""

from __future__ import annotations

import os
import pathlib
import random
import re
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from mcrs.experiment.config import ConfigError, validate
from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.training.trainer import Experiment
from mcrs.train import resume_config
from tests.train_helpers import compose_config

pytestmark = pytest.mark.slow


class _TouchOnLoad:
    """Unpickling this object would create ``marker``: the proof that loading ran code."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (pathlib.Path.touch, (pathlib.Path(self.marker),))


@pytest.fixture(scope="module")
def good_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    run_dir = tmp_path_factory.mktemp("good") / "run"
    Experiment(compose_config("train.total_env_steps=40"), run_dir).run()
    return run_dir


def _pickled_callable(path: Path, marker: Path) -> None:
    torch.save({"format": ckpt.FORMAT, "version": ckpt.VERSION, "payload": _TouchOnLoad(marker)}, path)


def _blocked_module_global(path: Path, marker: Path) -> None:
    """A callable from a module torch's safe loader blocks (os.system): torch's own text advises loading
    with weights_only=False; our error must not."""
    torch.save({"format": ckpt.FORMAT, "version": ckpt.VERSION, "payload": _System()}, path)


class _System:
    def __reduce__(self):
        return (os.system, ("true",))


def _truncated(good: Path) -> Callable[[Path, Path], None]:
    def write(path: Path, marker: Path) -> None:
        data = good.read_bytes()
        path.write_bytes(data[: len(data) // 2])

    return write


def _random_bytes(path: Path, marker: Path) -> None:
    path.write_bytes(random.Random(0).randbytes(64 * 1024))


def _foreign_state_dict(path: Path, marker: Path) -> None:
    torch.save(torch.nn.Linear(3, 2).state_dict(), path)  # a plain torch file without our markers


def _empty(path: Path, marker: Path) -> None:
    path.write_bytes(b"")


def _future_version(path: Path, marker: Path) -> None:
    torch.save({"format": ckpt.FORMAT, "version": ckpt.VERSION + 1}, path)


def _bad_files(good: Path) -> dict[str, tuple[Callable[[Path, Path], None], str]]:
    """name -> (writer, the reason the error must give)."""
    return {
        "pickled_callable": (
            _pickled_callable,
            r"needs code to load \(Unsupported global: .*\); refused without",
        ),
        "blocked_module_global": (
            _blocked_module_global,
            r"needs code to load \(posix\.system, from the blocked module posix\); refused without running it$",
        ),
        "truncated": (_truncated(good), "it is truncated or corrupt"),
        "random_bytes": (_random_bytes, "it is corrupt or not a torch file"),
        "foreign_state_dict": (_foreign_state_dict, "is not an mcrs checkpoint"),
        "empty": (_empty, "the file is empty"),
        "future_version": (_future_version, f"has checkpoint version {ckpt.VERSION + 1}; this mcrs reads"),
    }


BAD = [
    "pickled_callable",
    "blocked_module_global",
    "truncated",
    "random_bytes",
    "foreign_state_dict",
    "empty",
    "future_version",
]


@pytest.mark.parametrize("kind", BAD)
def test_load_refuses_bad_file_without_running_code(kind: str, good_run: Path, tmp_path: Path) -> None:
    writer, reason = _bad_files(ckpt.checkpoint_path(good_run))[kind]
    marker = tmp_path / "code_ran"
    path = tmp_path / "last.pt"
    writer(path, marker)
    with pytest.raises(ckpt.CheckpointError, match=reason) as info:
        ckpt.load(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)
    assert "weights_only" not in str(info.value)  # never advice to load unsafely
    assert not marker.exists(), "loading the checkpoint ran code"


def test_the_pickled_callable_would_run_code_if_loaded_unsafely(tmp_path: Path) -> None:
    """Guards the test above: the file really carries code (an unsafe load creates the marker)."""
    marker, path = tmp_path / "code_ran", tmp_path / "evil.pt"
    _pickled_callable(path, marker)
    torch.load(path, weights_only=False)
    assert marker.exists()


def _cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "mcrs.train", *args],
        cwd=cwd,
        env={**os.environ, "HYDRA_FULL_ERROR": "0"},
        capture_output=True,
        text=True,
        timeout=300,
    )


@pytest.mark.parametrize("kind", BAD)
def test_cli_resume_refuses_bad_last_pt_in_one_line(kind: str, good_run: Path, tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    shutil.copytree(good_run, run_dir)
    last = ckpt.checkpoint_path(run_dir)
    writer, reason = _bad_files(ckpt.checkpoint_path(good_run))[kind]
    marker = tmp_path / "code_ran"
    writer(last, marker)
    done = _cli(f"resume={run_dir}", cwd=tmp_path)
    assert done.returncode != 0
    error_lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert "Traceback" not in done.stderr, done.stderr
    assert error_lines[-1].startswith("mcrs-train: error: "), done.stderr
    assert len([line for line in error_lines if "error" in line.lower()]) == 1, done.stderr
    assert re.search(reason, error_lines[-1]), error_lines[-1]
    assert not marker.exists()


def test_config_values_are_data_not_code(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    code = "__import__('os').system('touch pwned')"
    cfg = compose_config(f'logger.project="{code}"', "train.total_env_steps=20")
    validate(cfg)
    Experiment(cfg, tmp_path / "run").run()
    assert cfg.logger.project == code  # kept as a plain string
    assert not (tmp_path / "pwned").exists()
    saved = OmegaConf.load(tmp_path / "run" / "config.yaml")
    assert saved.logger.project == code


def test_only_omegaconfs_data_resolvers_exist() -> None:
    """``${oc.env:...}`` reads a variable (a resolver, not code); there is no eval-like resolver."""
    cfg = compose_config("logger.project='${oc.env:HOME}'")
    assert cfg.logger.project == os.environ["HOME"]
    for expression in ("${eval:1+1}", "${python:os.system}"):
        cfg = compose_config(f"logger.project='{expression}'")
        with pytest.raises(ConfigError, match=r"logger\.project: Unsupported interpolation type"):
            validate(cfg)  # one line naming the field, as any bad config


def test_a_tampered_run_config_is_not_executed(good_run: Path, tmp_path: Path) -> None:
    """``resume`` reads the run's config.yaml with a safe YAML loader: python tags are refused."""
    run_dir = tmp_path / "run"
    shutil.copytree(good_run, run_dir)
    marker = tmp_path / "code_ran"
    (run_dir / "config.yaml").write_text(
        f"seed: !!python/object/apply:pathlib.Path.touch [!!python/object/apply:pathlib.Path ['{marker}']]\n"
    )
    with pytest.raises(Exception, match="python/object"):
        resume_config(compose_config(f"resume={run_dir}"), [f"resume={run_dir}"])
    assert not marker.exists()


def test_wandb_is_offline_by_default(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The default logger config sends nothing: even with WANDB_MODE=online in the environment."""
    pytest.importorskip("wandb")
    from mcrs.experiment.run.logging import make_logger

    cfg = compose_config("logger=wandb")
    assert cfg.logger.wandb_mode == "offline"
    monkeypatch.setenv("WANDB_MODE", "online")
    monkeypatch.setenv("WANDB_SILENT", "true")
    logger = make_logger("wandb", tmp_path, {"seed": 0}, cfg.logger.project, cfg.logger.wandb_mode)
    try:
        assert os.environ["WANDB_MODE"] in ("offline", "dryrun")
        assert logger.experiment.settings.mode in ("offline", "dryrun")
        assert list((tmp_path / "wandb").glob("offline-run-*"))
        assert not list((tmp_path / "wandb").glob("run-*"))  # an online run's folder
    finally:
        logger.experiment.finish()
