"""The trainer's and tools' promises tried as a hostile user would: a Hydra callback or Hydra's own files
moved out of the run from a campaign file or the command line, a run killed between its last checkpoint
and its final evaluation, a document rewritten over lines added meanwhile, damaged checkpoints, and values
whose arithmetic overflows. Each test is one reproduction: it failed before the fix.
"""

from __future__ import annotations

import importlib
import logging
import re
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


#: (override, what it would have written outside, the refusal): Hydra's own files and logs moved out of the run.
HYDRA_FILES_AND_LOGS = [
    ("hydra.output_subdir=../../../x", "x", "Hydra's files go in a folder inside the run directory"),
    ("hydra.job_logging.handlers.file.filename={tmp}/elsewhere.log", "elsewhere.log",
     "the command's log is written in its run directory"),
    ("hydra.job.name=../../../job", "job.log", "the job's name names its log file in the run directory"),
    ("~hydra.callbacks.run_dir_check", None, "adds, changes or removes a Hydra callback"),
    # another set of handlers: the log would open, and Hydra write .hydra/, before a sweep's job is claimed
    ("hydra/job_logging=default", None, "the command's log is written in its run directory"),
]  # fmt: skip
#: Overrides refused on the command line before Hydra starts: the callback and the cases above.
COMMAND_LINE_REFUSALS = 1 + len(HYDRA_FILES_AND_LOGS)


@pytest.mark.parametrize(
    ("override", "outside", "expected"),
    HYDRA_FILES_AND_LOGS,
    ids=["output_subdir", "log_file", "job_name", "remove_check", "log_handlers"],
)
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
    from mcrs.experiment.commands.cli import command_line_problems

    assert command_line_problems(["hydra.run.dir=/tmp/x", "hydra.output_subdir=null", "hydra/launcher=joblib",
                                  "hydra.output_subdir=meta/hydra", "hydra.job_logging.root.level=WARNING",
                                  "hydra.sweep.dir=s", "-m", "--config-dir=/x", "train.lr=1e-3"]) == []  # fmt: skip


# ------------------------------------------------------------------- a kill before the final evaluation
#: Runs ``Experiment`` in a child that SIGKILLs itself at one point of the run's end (``argv``: the point,
#: the run directory, the overrides).
_KILLED_AT = """
import os, signal, sys
from mcrs.experiment.run import run_state
from mcrs.experiment.training.trainer import Experiment
from tests.train_helpers import compose_config

point, run_dir, *overrides = sys.argv[1:]
cfg = compose_config(*overrides)
total = int(cfg.train.total_env_steps)
kill = lambda: os.kill(os.getpid(), signal.SIGKILL)
real_evaluate, real_save, real_atomic = Experiment.evaluate, run_state.RunState.save, run_state.ckpt.save_atomic
saves = []

def evaluate(self):  # "window": after the last batch's checkpoint, before the final evaluation
    if point == "window" and self.counters.env_steps >= total:
        kill()
    return real_evaluate(self)

def save(self, name="last.pt"):  # "evaluated": the final evaluation logged, not yet saved
    if point == "evaluated" and self.evaluated_at == total:
        kill()
    return real_save(self, name)

def save_atomic(payload, path):  # "saving": the final last.pt written, its weights file not
    out = real_atomic(payload, path)
    if path.name == "last.pt" and payload["counters"]["env_steps"] == total:
        saves.append(path)
        if point == "saving" and len(saves) == 2:
            kill()
    return out

Experiment.evaluate, run_state.RunState.save, run_state.ckpt.save_atomic = evaluate, save, save_atomic
Experiment(cfg, run_dir).run()
"""
#: A budget that is a multiple of checkpoint_interval: the last batch's checkpoint is at the run's end.
_WINDOW = ["train.total_env_steps=120", "train.checkpoint_interval=40", "train.eval_interval=40"]
KILL_POINTS = ["window", "evaluated", "saving"]


def _csv_rows(run_dir: Path) -> dict[str, list[str]]:
    """Every CSV log but the wall-clock timings (``time/``), by name."""
    root = run_dir / "logs" / "scalars"
    return {
        p.relative_to(root).as_posix(): p.read_text().splitlines()
        for p in sorted(root.rglob("*.csv"))
        if not p.relative_to(root).as_posix().startswith("time/")
    }


@pytest.fixture(scope="module")
def straight_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from mcrs.experiment.training.trainer import Experiment
    from tests.train_helpers import compose_config

    run_dir = tmp_path_factory.mktemp("straight") / "run"
    Experiment(compose_config(*_WINDOW), run_dir).run()
    return run_dir


@pytest.mark.slow
@pytest.mark.parametrize("point", KILL_POINTS)
def test_a_run_killed_before_its_final_evaluation_resumes_to_the_straight_runs_rows(
    point: str, straight_run: Path, tmp_path: Path
) -> None:
    """Killed between its last checkpoint (at the budget, a multiple of ``checkpoint_interval``) and its
    final evaluation, a run resumed to "nothing to train" and gave the previous evaluation as the final
    one; its evaluation CSVs never got the last row. Now it is finished only once that row is written: the
    resumed run's CSVs are the straight run's, at each point of the run's end."""
    import os
    import subprocess

    from mcrs.experiment.run import checkpoint as ckpt
    from mcrs.experiment.training.trainer import Experiment
    from mcrs_lab.analysis.records import training_record
    from tests.train_helpers import compose_config

    run_dir = tmp_path / "run"
    root = Path(__file__).resolve().parents[1]
    done = subprocess.run([sys.executable, "-c", _KILLED_AT, point, str(run_dir), *_WINDOW], cwd=root,
                          capture_output=True, text=True, timeout=600,
                          env={**os.environ, "PYTHONPATH": str(root)})  # fmt: skip
    assert done.returncode == -9, done.stderr  # SIGKILL
    assert ckpt.load(ckpt.checkpoint_path(run_dir))["counters"]["env_steps"] == 120
    if point == "window":  # not finished: a record says stopped, a resume evaluates
        assert training_record(run_dir)["status"] == "stopped"
    result = Experiment(compose_config(*_WINDOW), run_dir, resume=True).run()
    assert _csv_rows(run_dir) == _csv_rows(straight_run)
    eval_rows = _csv_rows(run_dir)["eval/episode_reward.csv"]
    assert [int(float(r.split(",")[0])) for r in eval_rows] == [0, 40, 80, 120]
    assert result["episode_reward"] == float(eval_rows[-1].split(",")[1])
    assert training_record(run_dir)["status"] == "finished"


class _Killed(BaseException):
    """Stands for a kill in the process (raised where the run would die)."""


def _without_last_eval_step(run_dir: Path) -> None:
    """``last.pt`` as a checkpoint written before it named its last evaluation's step."""
    from mcrs.experiment.run import checkpoint as ckpt

    path = ckpt.checkpoint_path(run_dir)
    state = ckpt.load(path)
    del state["last_eval_step"]
    ckpt.save_atomic({k: v for k, v in state.items() if k not in ("format", "version")}, path)


@pytest.mark.parametrize("finished", [False, True], ids=["killed_in_the_window", "finished"])
def test_a_checkpoint_from_before_last_eval_step_is_judged_by_its_evaluation_log(
    finished: bool,
    straight_run: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Checkpoints users and a running campaign hold today carry no ``last_eval_step``: a finished one
    stays finished (nothing is evaluated or logged again), one killed in the window is evaluated."""
    from mcrs.experiment.training.trainer import Experiment
    from tests.train_helpers import compose_config

    run_dir = tmp_path / "run"
    if finished:
        Experiment(compose_config(*_WINDOW), run_dir).run()
    else:
        real = Experiment.evaluate

        def evaluate(self: Experiment) -> dict[str, float]:
            if self.counters.env_steps >= 120:
                raise _Killed
            return real(self)

        monkeypatch.setattr(Experiment, "evaluate", evaluate)
        with pytest.raises(_Killed):
            Experiment(compose_config(*_WINDOW), run_dir).run()
        monkeypatch.setattr(Experiment, "evaluate", real)
    _without_last_eval_step(run_dir)
    with caplog.at_level(logging.INFO, logger="mcrs.run"):
        experiment = Experiment(compose_config(*_WINDOW), run_dir, resume=True)
        assert experiment.finished == finished
    assert "was written before checkpoints named their last evaluation's step: judged by" in caplog.text
    experiment.run()
    assert _csv_rows(run_dir) == _csv_rows(straight_run)


# ------------------------------------------------------------------------------------- checkpoints
@pytest.fixture(scope="module")
def two_runs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Two finished 40-step runs of the same config (their checkpoints share a fingerprint)."""
    from mcrs.experiment.training.trainer import Experiment
    from tests.train_helpers import compose_config

    root = tmp_path_factory.mktemp("runs")
    for name in ("a", "b"):
        Experiment(
            compose_config("train.total_env_steps=40", "train.checkpoint_interval=40"), root / name
        ).run()
    return root / "a", root / "b"


def _copy(run: Path, tmp_path: Path) -> Path:
    import shutil

    shutil.copytree(run, tmp_path / "run")
    return tmp_path / "run"


def _edit(run_dir: Path, change) -> None:
    """Rewrite ``last.pt`` with ``change`` applied (a consistent file, checksum included)."""
    from mcrs.experiment.run import checkpoint as ckpt

    path = ckpt.checkpoint_path(run_dir)
    state = ckpt.load(path)
    change(state)
    ckpt.save_atomic({k: v for k, v in state.items() if k not in ("format", "version", "checksum")}, path)


def _resume_refused(run_dir: Path) -> str:
    from mcrs.experiment.run import checkpoint as ckpt
    from mcrs.experiment.training.trainer import Experiment
    from tests.train_helpers import compose_config

    cfg = compose_config("train.total_env_steps=80", "train.checkpoint_interval=40")
    with pytest.raises(ckpt.CheckpointError) as refused:
        Experiment(cfg, run_dir, resume=True)
    message = str(refused.value)
    assert "\n" not in message and str(ckpt.checkpoint_path(run_dir)) in message, message
    return message


def _flip_a_weight_byte(path: Path) -> None:
    """One byte flipped in the middle of the agent's first weight tensor, in place."""
    import torch

    state = torch.load(path, weights_only=True)
    tensor = next(iter(state["learner"]["agent"].values()))
    data = path.read_bytes()
    at = data.find(tensor.contiguous().numpy().tobytes()) + tensor.numel() * tensor.element_size() // 2
    assert at > 0
    path.write_bytes(data[:at] + bytes([data[at] ^ 0x10]) + data[at + 1 :])


def test_a_flipped_byte_in_a_checkpoints_tensor_is_refused(
    two_runs: tuple[Path, Path], tmp_path: Path
) -> None:
    """A checkpoint with one byte flipped in a weight resumed with corrupted weights (torch does not check
    a zip member's CRC). Now its checksum refuses it, naming the file and the entry, for a resume and for
    ``mcrs-eval``'s weights file."""
    from mcrs.experiment.run import checkpoint as ckpt

    run_dir = _copy(two_runs[0], tmp_path)
    last = ckpt.checkpoint_path(run_dir)
    _flip_a_weight_byte(last)
    message = _resume_refused(run_dir)
    assert message.endswith(f"checkpoint {last}: entry learner: its data does not match the checksum written "
                            "with it: the file is damaged; refused (use an earlier checkpoint or run again)")  # fmt: skip
    weights = ckpt.weights_path(run_dir, 40)
    _flip_a_weight_byte(weights)
    with pytest.raises(
        ckpt.CheckpointError, match=rf"^checkpoint {weights}: entry learner: its data does not"
    ):
        ckpt.load(weights)


def test_a_checkpoint_without_a_checksum_loads_and_says_so(
    two_runs: tuple[Path, Path], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Checkpoints written before checksums existed (users' and a running campaign's) still resume."""
    import torch

    from mcrs.experiment.run import checkpoint as ckpt
    from mcrs.experiment.training.trainer import Experiment
    from tests.train_helpers import compose_config

    run_dir = _copy(two_runs[0], tmp_path)
    for path in (run_dir / "checkpoints").glob("*.pt"):
        state = torch.load(path, weights_only=True)
        del state["checksum"]
        torch.save(state, path)
    with caplog.at_level(logging.INFO, logger="mcrs.run"):
        Experiment(compose_config("train.total_env_steps=80", "train.checkpoint_interval=40"), run_dir,
                   resume=True).run()  # fmt: skip
    assert "was written before checksums existed: its data is read unverified" in caplog.text
    assert ckpt.load(ckpt.checkpoint_path(run_dir))["counters"]["env_steps"] == 80


def _manifest_names_another_run(other: Path, run_dir: Path):
    """The first replay block named through ``..`` as the other run's block file."""
    import os

    def change(state: dict) -> None:
        name = state["replay_blocks"]["files"][0]
        theirs = os.path.relpath(other / "checkpoints" / name, run_dir / "checkpoints")
        assert theirs.startswith("../../") and Path(run_dir / "checkpoints" / theirs).is_file()
        state["replay_blocks"]["files"][0] = theirs

    return change


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        ("manifest", "entry replay_blocks.files[0]: '../../"),
        (lambda s: s["counters"].update(env_steps=-1000), "entry counters.env_steps: -1000 is not a whole number >= 0"),
        (lambda s: s["counters"].update(update_credit=float("nan")), "entry counters.update_credit: nan is not a finite number >= 0"),
        (lambda s: s["counters"].update(episodes="12"), "entry counters.episodes: '12' is not a whole number >= 0"),
        (lambda s: s["counters"].update(updates=1.5), "entry counters.updates: 1.5 is not a whole number >= 0"),
        (lambda s: s.update(counters=[1, 2]), "entry counters: [1, 2] is not a mapping of counters"),
        (lambda s: s["rng"].update(torch=s["rng"]["torch"][:100]), "entry rng.torch: a torch.uint8 tensor of 100 is not a random state"),
        (lambda s: s["rng"].update(torch=s["rng"]["torch"].float()), "entry rng.torch: a torch.float32 tensor of"),
        (lambda s: s["rng"].update(torch="seed"), "entry rng.torch: 'seed' is not a random state"),
        (lambda s: s.update(last_eval_step=-3), "entry last_eval_step: -3 is not a whole number >= 0"),
        (lambda s: s.update(last_eval={"episode_reward": "high"}), "entry last_eval: {'episode_reward': 'high'}"),
        (lambda s: s.update(logs={"rows": {"eval/x": -1}}), "entry logs.rows: {'eval/x': -1}"),
    ],
    ids=["manifest", "negative_steps", "nan_credit", "string_counter", "float_counter", "counters_list",
         "short_rng", "float_rng", "string_rng", "negative_eval_step", "string_metric", "negative_rows"],
)  # fmt: skip
def test_a_damaged_checkpoint_entry_is_refused_naming_it(
    change, expected: str, two_runs: tuple[Path, Path], tmp_path: Path
) -> None:
    """A manifest naming ``../../other_run/...`` read another run's replay; negative or NaN counters were
    accepted; a wrong-sized random state or a counter of the wrong type gave a traceback."""
    run_dir = _copy(two_runs[0], tmp_path)
    _edit(run_dir, _manifest_names_another_run(two_runs[1], run_dir) if change == "manifest" else change)
    assert expected in _resume_refused(run_dir)


# -------------------------------------------------------------------------------- mcrs-results update
RECORDS = Path("results/records/near/heuristics/map20")  # committed evaluations


def _document(tmp_path: Path) -> Path:
    """A copy of the heuristic records and a document under docs/ with one stale generated table."""
    import shutil

    shutil.copytree(RECORDS, tmp_path / RECORDS)
    doc = tmp_path / "docs" / "R.md"
    doc.parent.mkdir()
    doc.write_text(f"# R\n\n<!-- table evaluations.md of: mcrs-report {RECORDS} --env map20 -->\n| stale |\n"
                   "<!-- end table -->\n")  # fmt: skip
    return doc


def test_mcrs_results_update_keeps_a_line_added_while_it_generated(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``mcrs-results update`` read the document, generated for 40-60 s, then wrote its old copy back: a
    line added meanwhile was lost. Now the update is refused in one line and the line stays."""
    import mcrs_lab.analysis.doc_tables as doc_tables

    doc = _document(tmp_path)
    real = doc_tables.generate

    def generate_while_edited(blocks, root):
        made = real(blocks, root)
        with open(doc, "a") as f:
            f.write("a line written while the tables were generated\n")
        return made

    monkeypatch.setattr(doc_tables, "generate", generate_while_edited)
    edited = None
    with pytest.raises(SystemExit) as refused:
        doc_tables.main(["update", str(doc)])
        edited = doc.read_text()
    assert refused.value.code == (
        f"mcrs-results: error: {doc} changed since it was read: nothing written (the change is kept); run again"
    )
    assert edited is None and doc.read_text().endswith("| stale |\n<!-- end table -->\na line written while "
                                                       "the tables were generated\n")  # fmt: skip
    assert sorted(p.name for p in doc.parent.iterdir()) == ["R.md"]  # no temporary left


def test_mcrs_results_update_writes_through_a_temporary_of_its_own(tmp_path: Path) -> None:
    """Two updates shared one temporary name (``.R.md.partial``): whatever sat at that name (another
    update's half-written copy, or a link to a file elsewhere) was written through and renamed over the
    document. Now each update writes a temporary of its own and the file at that name is left alone."""
    from mcrs_lab.analysis.doc_tables import main

    doc = _document(tmp_path)
    victim = _victim(tmp_path)
    (doc.parent / f".{doc.name}.partial").symlink_to(victim)
    assert main(["update", str(doc)]) == 0
    assert victim.read_text() == "precious\n"
    assert not doc.is_symlink() and "| greedy (heuristic)" in doc.read_text()


# -------------------------------------------------------------------------------- one run, one claim
@pytest.mark.slow
def test_a_second_command_into_a_starting_run_is_refused_before_it_writes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two ``mcrs-train`` started together into one ``hydra.run.dir`` (different algo and seed): the run
    trained one config while ``.hydra/config.yaml`` held the other's, and the refused process logged into
    the winner's ``train.log`` (the lock was taken after torch loaded). Now the first claims the directory
    before Hydra writes there; the second, started while the first still loads, is refused and writes
    nothing."""
    import os
    import subprocess
    import time

    from tests.train_helpers import TINY

    run_dir = tmp_path / "run"
    root = Path(__file__).resolve().parents[1]
    first = subprocess.Popen([sys.executable, "-m", "mcrs.train", f"hydra.run.dir={run_dir}", "algo=qmix", "seed=0",
                              *TINY], cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             env={**os.environ, "PYTHONPATH": str(root), "HYDRA_FULL_ERROR": "0"})  # fmt: skip
    hydra_config = run_dir / ".hydra" / "config.yaml"
    last = run_dir / ".hydra" / "overrides.yaml"  # Hydra writes config, hydra, overrides in turn
    deadline = time.monotonic() + 120
    while (
        not (last.exists() and last.stat().st_size) and first.poll() is None and time.monotonic() < deadline
    ):
        time.sleep(0.05)
    assert hydra_config.exists(), first.communicate()
    time.sleep(0.2)  # the last file's write done
    written = {p: p.read_bytes() for p in hydra_config.parent.iterdir()}  # Hydra's files of the first run
    try:
        message = _refused(monkeypatch, tmp_path, "mcrs.train", f"hydra.run.dir={run_dir}", "algo=vdn", "seed=1",
                           *TINY)  # fmt: skip
        assert message == (
            f"mcrs-train: error: run directory {run_dir} is in use by process {first.pid}: one process writes "
            "a run; wait for it to end (then resume=), or choose another directory"
        )
        assert {p: p.read_bytes() for p in written} == written  # the first run's files as they were
    finally:
        _out, err = first.communicate(timeout=600)
    assert first.returncode == 0, err
    import yaml

    assert yaml.safe_load(hydra_config.read_text())["algo"]["name"] == "qmix"
    assert yaml.safe_load((run_dir / "config.yaml").read_text())["algo"]["name"] == "qmix"
    assert (
        "vdn" not in (run_dir / "train.log").read_text()
        and "in use" not in (run_dir / "train.log").read_text()
    )


def _held(lock: Path):
    """Another process holding ``lock`` as a live run holds its run's: an exclusive ``flock``, its PID in it."""
    import subprocess

    code = (
        "import fcntl, os, socket, sys, time\n"
        "fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT, 0o644)\n"
        "fcntl.flock(fd, fcntl.LOCK_EX)\n"
        "os.pwrite(fd, f'{os.getpid()} {socket.gethostname()}\\n'.encode(), 0)\n"
        "print('held', flush=True)\n"
        "time.sleep(600)\n"
    )
    holder = subprocess.Popen([sys.executable, "-c", code, str(lock)], stdout=subprocess.PIPE, text=True)
    assert holder.stdout is not None and holder.stdout.readline() == "held\n"
    return holder


def _files(directory: Path) -> dict[str, bytes | None]:
    """Every file and folder under ``directory`` (hidden ones too), with a file's bytes."""
    return {
        p.relative_to(directory).as_posix(): p.read_bytes() if p.is_file() else None
        for p in sorted(directory.rglob("*"))
    }


@pytest.mark.parametrize("other", ["live", "finished"])
def test_a_sweep_job_is_refused_before_hydra_writes_into_its_folder(
    other: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``mcrs-train -m``: Hydra makes each job's folder and writes its ``.hydra/`` and ``train.log`` before
    the trainer runs, so a job whose folder held a live run (a concurrent sweep's job, a single run)
    overwrote that run's ``.hydra/config.yaml`` and logged its refusal into the run's ``train.log``, and a
    job whose folder held a finished run rewrote its ``.hydra/``. Now each job claims its folder first:
    the sweep stops at that job in one line naming what holds the folder, and every file there is as it
    was."""
    from tests.train_helpers import TINY

    sweep = tmp_path / "sweep"
    job = sweep / "0_map10_qmix_seed0"  # the first job's folder (hydra.sweep.subdir)
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "config.yaml").write_text("algo:\n  name: vdn\nseed: 1\n")
    (job / "train.log").write_text("[2026-01-01 00:00:00][mcrs.run][INFO] the other run\n")
    if other == "finished":
        (job / "config.yaml").write_text("algo:\n  name: vdn\nseed: 1\n")
        (job / "checkpoints").mkdir()
        (job / "checkpoints" / "last.pt").write_bytes(b"the other run's checkpoint")
    holder = _held(job / ".mcrs.lock") if other == "live" else None
    before = _files(job)
    try:
        message = _refused(monkeypatch, tmp_path, "mcrs.train", "-m", f"hydra.sweep.dir={sweep}", "algo=qmix",
                           "seed=0,1", *TINY)  # fmt: skip
        assert _files(job) == before  # the lock file too: its holder's PID
    finally:
        if holder is not None:
            holder.kill()
            holder.wait()
    held = (
        f"run directory {job} is in use by process {holder.pid}"
        if holder
        else f"run directory {job} is not empty"
    )
    assert message.startswith("mcrs-train: error: sweep job 0: ") and held in message, message
    assert message.endswith("; the sweep stops: no later job was started"), message
    assert sorted(p.name for p in sweep.iterdir() if not p.name.startswith((".", "multirun"))) == [job.name]


# ------------------------------------------------------------------------ values, names and full disks
@pytest.mark.parametrize(
    ("overrides", "expected"),
    [
        (["env.name=${now:%H-%M}"], "env.name=${now:%H-%M}: must be a plain name, not an interpolation"),
        (["env.name=map20"], "env.name='map20' names the preset env=map20, but this run has width=10 (the preset's 20)"),
        (["env.p_detect=0.2", "env.p_false_alarm=0.8"], "p_detect=0.2 < p_false_alarm=0.8: the sensor would read backwards"),
        (["train.lr=1e300"], "train.lr=1e+300: must be <= 1"),
        (["env.comm_range=1e308"], "env.comm_range=1e+308: must be <= 1e+09 cells or inf"),
    ],
    ids=["interpolated_name", "preset_name", "backwards_sensor", "huge_lr", "huge_range"],
)  # fmt: skip
def test_nonsense_values_are_refused_before_anything_runs(
    overrides: list[str], expected: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``env.name=${now:%H-%M}`` filed a map10 run under another name, ``env.name=map20`` passed a map10
    run for map20, a sensor reading backwards was accepted, and ``train.lr=1e300`` or
    ``env.comm_range=1e308`` ended in an overflow's traceback."""
    message = _refused(monkeypatch, tmp_path, "mcrs.train", *overrides)
    assert message.startswith("mcrs-train: error: invalid config: ") and expected in message, message
    assert list(tmp_path.iterdir()) == []


def test_the_sensors_that_make_sense_pass() -> None:
    """The default sensor, a perfect one and an uninformative one (always F: used to test the discovery
    reward) are not backwards."""
    from mcrs.env.config import EnvConfig, validation_errors

    for p_detect, p_false_alarm in ((0.8, 0.2), (1.0, 0.0), (1.0, 1.0), (0.5, 0.5)):
        assert validation_errors(EnvConfig(p_detect=p_detect, p_false_alarm=p_false_alarm)) == []


def test_mcrs_eval_on_a_full_disk_is_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``mcrs-eval`` on a full disk printed 86 lines of OSError."""
    import errno

    import mcrs.evaluate

    def full(*args: object, **kwargs: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(mcrs.evaluate, "write_results", full)
    out = tmp_path / "out"
    message = _refused(monkeypatch, tmp_path, "mcrs.evaluate", "episodes=1", "figures=false", "env.max_steps=5",
                       f"hydra.run.dir={out}")  # fmt: skip
    assert message == f"mcrs-eval: error: cannot write {out}: No space left on device", message


def test_the_documented_counts_are_the_suites() -> None:
    """README.md and docs/RELIABILITY.md state the refused overrides (campaign files and command line) and
    the kill points of a run's end that these tests try."""
    from tests.test_bad_inputs_tools import BAD_CAMPAIGN_OVERRIDES

    overrides = len(BAD_CAMPAIGN_OVERRIDES) + COMMAND_LINE_REFUSALS
    root = Path(__file__).resolve().parents[1]
    for doc in ("README.md", "docs/RELIABILITY.md"):
        text = " ".join((root / doc).read_text().split())
        found = {int(n) for n in re.findall(r"(\d+) refused overrides", text)}
        assert found == {overrides}, (
            f"{doc} states {sorted(found)} refused overrides; the suite tries {overrides}"
        )
        kills = {int(n) for n in re.findall(r"(\d+) kill points", text)}
        assert kills == {len(KILL_POINTS)}, (
            f"{doc} states {sorted(kills)} kill points; the suite has {len(KILL_POINTS)}"
        )
