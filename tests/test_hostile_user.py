"""The trainer's and tools' promises tried as a hostile user would: a Hydra callback or Hydra's own files
moved out of the run from a campaign file or the command line, a run killed between its last checkpoint
and its final evaluation, a document rewritten over lines added meanwhile, damaged checkpoints, and values
whose arithmetic overflows. Each test is one reproduction: it failed before the fix.
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import pytest

from mcrs_lab.campaign.cli import main as campaign_main

# ----------------------------------------------------------------------------- overrides from files
POINTS = """
budget: smoke
seeds: [0]
figures:
  figa:
    experiment: comm_range
    env: [map10]
    algo: [qmix]
    sweep: {env.comm_range: [0]}
"""


def _victim(tmp_path: Path) -> Path:
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    return victim


def _campaign(tmp_path: Path, overrides: list[str]) -> list[str]:
    matrix = tmp_path / "m.yaml"
    listed = ", ".join(f"'{o}'" for o in overrides)
    matrix.write_text(POINTS + f"overrides:\n  all: [{listed}]\n")
    return ["--matrix", str(matrix), "--outputs", str(tmp_path / "out"), "--records", str(tmp_path / "rec")]


@pytest.mark.parametrize(
    ("overrides", "expected"),
    [
        (
            ["+hydra.callbacks.x._target_=builtins.open", "+hydra.callbacks.x.file={victim}", "+hydra.callbacks.x.mode=w"],
            "+hydra.callbacks.x._target_=builtins.open: a Hydra setting",
        ),
        (["hydra.output_subdir=../../../.."], "hydra.output_subdir=../../../..: a Hydra setting"),
        (["resume={victim}"], "set by the tool for each run"),
    ],
    ids=["callback", "output_subdir", "resume"],
)  # fmt: skip
@pytest.mark.parametrize(
    "command", [["status"], ["run", "--hours", "1", "--dry-run"], ["run", "--hours", "1"]]
)
def test_a_campaign_files_hydra_override_is_refused_by_status_dry_run_and_run(
    overrides: list[str], expected: str, command: list[str], tmp_path: Path
) -> None:
    """A campaign file's ``overrides:`` reached ``mcrs-train`` unchecked: a callback truncated a file
    outside every root, ``hydra.output_subdir`` wrote ``.hydra/`` outside ``--outputs``, and ``status`` and
    ``--dry-run`` listed the point without a word. Now each command refuses the file in one line."""
    victim = _victim(tmp_path)
    args = _campaign(tmp_path, [o.format(victim=victim) for o in overrides])
    with pytest.raises(SystemExit) as info:
        campaign_main([*command, *args])
    message = str(info.value.code)
    assert message.startswith("mcrs-campaign: error: ") and "\n" not in message, message
    assert f"{tmp_path / 'm.yaml'}: overrides all: " in message and expected in message, message
    assert victim.read_text() == "precious\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.yaml", "victim.txt"]


def test_an_evaluation_variants_hydra_override_is_refused(tmp_path: Path) -> None:
    """``mcrs-campaign evaluate`` passed a variant's overrides to ``mcrs-eval`` unchecked."""
    matrix = tmp_path / "m.yaml"
    matrix.write_text(
        POINTS + "evaluations:\n  e:\n    of: [figa]\n    heuristics: [greedy]\n    episodes: 2\n"
        f"    seeds: [0]\n    variants:\n      a: ['hydra.sweep.dir={tmp_path}/elsewhere']\n"
    )
    with pytest.raises(SystemExit) as info:
        campaign_main(["evaluate", "--dry-run", "--matrix", str(matrix), "--outputs", str(tmp_path / "o")])
    message = str(info.value.code)
    assert f"evaluation e: variant a: hydra.sweep.dir={tmp_path}/elsewhere: a Hydra setting" in message, (
        message
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.yaml"]


# ---------------------------------------------------------------------- overrides on the command line
def _refused(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, module: str, *args: str) -> str:
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HYDRA_FULL_ERROR", "0")
    command = {"mcrs.train": "mcrs-train", "mcrs.evaluate": "mcrs-eval", "mcrs.render_episode": "mcrs-render"}
    monkeypatch.setattr(sys, "argv", [command[module], *args])
    with pytest.raises(SystemExit) as refused:
        importlib.import_module(module).main()
    message = refused.value.code
    assert isinstance(message, str) and "\n" not in message, message
    return message


@pytest.mark.parametrize("module", ["mcrs.train", "mcrs.evaluate", "mcrs.render_episode"])
def test_a_command_line_callback_is_refused_before_it_runs(
    module: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``+hydra.callbacks.x._target_=builtins.open`` with a path truncated the file before the config
    check refused the command (``train.lr=-1``)."""
    victim = _victim(tmp_path)
    message = _refused(monkeypatch, tmp_path, module, "+hydra.callbacks.x._target_=builtins.open",
                       f"+hydra.callbacks.x.file={victim}", "+hydra.callbacks.x.mode=w", "train.lr=-1")  # fmt: skip
    assert message.endswith(
        "error: +hydra.callbacks.x._target_=builtins.open: adds, changes or removes a Hydra callback, code "
        "Hydra runs before the command checks anything: refused (the command's own callbacks are fixed)"
    ), message
    assert victim.read_text() == "precious\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["victim.txt"]


@pytest.mark.parametrize(
    ("override", "outside", "expected"),
    [
        ("hydra.output_subdir=../../../x", "x", "Hydra's files go in a folder inside the run directory"),
        ("hydra.job_logging.handlers.file.filename={tmp}/elsewhere.log", "elsewhere.log",
         "the command's log is written in its run directory"),
        ("hydra.job.name=../../../job", "job.log", "the job's name names its log file in the run directory"),
        ("~hydra.callbacks.run_dir_check", None, "adds, changes or removes a Hydra callback"),
    ],
    ids=["output_subdir", "log_file", "job_name", "remove_check"],
)  # fmt: skip
def test_hydras_files_and_logs_stay_in_the_run_directory(
    override: str, outside: str | None, expected: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``hydra.output_subdir=../../..`` wrote ``.hydra/`` and ``hydra.job_logging...filename`` the log
    outside the run; both are refused before anything is written."""
    run_dir = tmp_path / "runs" / "a" / "run"
    message = _refused(monkeypatch, tmp_path, "mcrs.train", override.format(tmp=tmp_path), f"hydra.run.dir={run_dir}",
                       "train.lr=-1")  # fmt: skip
    assert message.startswith(f"mcrs-train: error: {override.format(tmp=tmp_path)}: {expected}"), message
    assert list(tmp_path.iterdir()) == [], sorted(map(str, tmp_path.rglob("*")))
    assert outside is None or not (tmp_path / outside).exists()


def test_the_allowed_hydra_overrides_still_pass() -> None:
    """Where a run goes, its launcher and its log levels stay the user's; ``null`` keeps no ``.hydra/``."""
    from mcrs.experiment.cli import command_line_problems

    assert command_line_problems(["hydra.run.dir=/tmp/x", "hydra.output_subdir=null", "hydra/launcher=joblib",
                                  "hydra.output_subdir=meta/hydra", "hydra.job_logging.root.level=WARNING",
                                  "hydra.sweep.dir=s", "-m", "--config-dir=/x", "train.lr=1e-3"]) == []  # fmt: skip
