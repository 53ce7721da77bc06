"""A refused command is one line of ours (the key, group or override, and what is allowed, closest match
first) and leaves no directory behind; the same line is :func:`mcrs.compose`'s :class:`ConfigError`."""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra.errors import HydraException
from omegaconf.errors import OmegaConfBaseException

import mcrs
from mcrs.experiment.config import ConfigError
from mcrs.experiment.util.messages import describe, ranked
from tests.train_helpers import compose_config

#: Hydra's own report, none of which may reach the user.
HYDRA_NOISE = ("HYDRA_FULL_ERROR", "To append", "+env.", "Config search path", "provider=", "In 'config'",
               "full_key", "object_type", "Traceback")  # fmt: skip


def _hydra_error(override: str) -> BaseException:
    with pytest.raises((HydraException, OmegaConfBaseException)) as info:
        compose_config(override)
    return info.value


@pytest.mark.parametrize(
    ("override", "expected"),
    [
        ("env.comm_rage=3", "env.comm_rage: unknown key; the keys of env (closest first): comm_range,"),
        ("train.lrr=1", "train.lrr: unknown key; the keys of train (closest first): lr,"),
        ("algo.mixr=qmix", "algo.mixr: unknown key; the keys of algo (closest first): mixer,"),
        ("algo.memory.capcity=1", "algo.memory.capcity: unknown key; the keys of algo.memory (closest first): capacity,"),
        ("logger.backnd=csv", "logger.backnd: unknown key; the keys of logger (closest first): backend,"),
        ("model.hiden_dim=3", "model.hiden_dim: unknown key; the keys of model (closest first): hidden_dim,"),
        ("sed=1", "sed: unknown key; the top-level keys (closest first): seed,"),
        ("algo=qmx", "algo=qmx: no such option of algo; allowed (closest first): qmix,"),
        ("algo=QMIX", "algo=QMIX: no such option of algo; allowed (closest first): qmix,"),
        ("total_env_steps=3200", "total_env_steps: unknown key (did you mean train.total_env_steps?); the top-level"),
        ("hidden_dim=32", "hidden_dim: unknown key (did you mean model.hidden_dim?); the top-level keys"),
        ("env=map99", "env=map99: no such option of env; allowed (closest first): map10, map15, map20"),
        ("logger=mlflow", "logger=mlflow: no such option of logger; allowed: csv, tensorboard, wandb"),
        ("hydra/launcher=jobib", "hydra/launcher=jobib: no such option of hydra/launcher; allowed (closest first): joblib,"),
        ("algo.mixer=qtran", "algo.mixer=qtran: allowed values: qmix, vdn, qplex"),
        ("train.lr=abc", "train.lr=abc: must be a number"),
        ("seed=x", "seed=x: must be an integer"),
        ("algo.double_q=maybe", "algo.double_q=maybe: must be true or false"),
        ("seed=[1", "cannot read the override 'seed=[1': no viable alternative at input '[1'"),
    ],
)  # fmt: skip
def test_a_composition_error_is_one_line_naming_the_key_and_what_is_allowed(
    override: str, expected: str
) -> None:
    line = describe(_hydra_error(override))
    assert line.startswith(expected), line
    assert "\n" not in line and not any(noise in line for noise in HYDRA_NOISE), line


def test_every_key_of_the_group_is_listed_once() -> None:
    line = describe(_hydra_error("env.comm_rage=3"))
    from mcrs.env.config import ScenarioConfig

    listed = line.split(": ", 2)[-1].split(", ")
    assert sorted(listed) == sorted(ScenarioConfig.__dataclass_fields__)


def test_ranked_puts_close_matches_first_and_keeps_the_rest_in_order() -> None:
    assert ranked("comm_rage", ["name", "width", "comm_rounds", "comm_range"]) == [
        "comm_range", "comm_rounds", "name", "width"]  # fmt: skip
    assert ranked("zzz", ["b", "a"]) == ["b", "a"]


def test_compose_raises_config_error_with_the_same_line() -> None:
    with pytest.raises(
        ConfigError, match=r"^env\.comm_rage: unknown key; the keys of env \(closest first\): comm_range"
    ):
        mcrs.compose("env.comm_rage=3")
    with pytest.raises(ConfigError, match=r"^algo=foo: no such option of algo; allowed"):
        mcrs.compose("algo=foo")


# ------------------------------------------------------------------ the commands (slow: processes)
def _start(module: str, cwd: Path, *args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", module, *args],
        cwd=cwd,
        env={**os.environ, "HYDRA_FULL_ERROR": "0", "PYTHONPATH": str(Path.cwd())},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


REFUSED = {
    ("mcrs.train", "env.comm_rage=3"): "mcrs-train: error: env.comm_rage: unknown key; the keys of env (closest first): comm_range,",
    ("mcrs.train", "algo=foo"): "mcrs-train: error: algo=foo: no such option of algo; allowed: cnn_semu, emc,",
    ("mcrs.train", "env=map99"): "mcrs-train: error: env=map99: no such option of env; allowed (closest first): map10, map15, map20",
    ("mcrs.train", "train.lr=-1"): "mcrs-train: error: invalid config:",
    ("mcrs.train", "device=cuda:7"): "mcrs-train: error: invalid config:",
    ("mcrs.train", "+env.widht=3"): "mcrs-train: error: invalid config: unknown field(s) env.widht",
    ("mcrs.train", "env.num_envs=4"): "mcrs-train: error: env.num_envs: not a scenario key (how the env runs, not the task): set train.num_envs (mcrs-train) or episodes (mcrs-eval)",
    ("mcrs.evaluate", "env.device=cpu"): "mcrs-eval: error: env.device: not a scenario key (how the env runs, not the task): set device",
    ("mcrs.train", "-m", "algo=qmix,foo"): "mcrs-train: error: algo=foo: no such option of algo",
    # A sweep's every job is checked before its first one starts (job 2 would fail after jobs 0 and 1 ran).
    ("mcrs.train", "-m", "train.lr=0.001,-1", "seed=0,1"): "mcrs-train: error: invalid config of sweep job 2 of 4 (train.lr=-1 seed=0): train.lr=-1.0: must be > 0; no job was started",
    ("mcrs.evaluate", "env.comm_rage=3"): "mcrs-eval: error: env.comm_rage: unknown key; the keys of env (closest first): comm_range,",
    ("mcrs.evaluate", "episodes=0"): "mcrs-eval: error: invalid config: episodes=0: must be >= 1",
    ("mcrs.render_episode", "env.comm_rage=3"): "mcrs-render: error: env.comm_rage: unknown key; the keys of env (closest first): comm_range,",
    ("mcrs.render_episode", "uav=9"): "mcrs-render: error: uav=9: must be in 0..3",
    ("mcrs.render_episode", "seed=-1"): "mcrs-render: error: seed=-1: must be in [0, 2**63 - 1]",
    ("mcrs.render_episode", "seed=99999999999999999999"): "mcrs-render: error: seed=99999999999999999999: must be in [0, 2**63 - 1]",
    ("mcrs.evaluate", "episodes=100001"): "mcrs-eval: error: invalid config: episodes=100001: at most 100000",
    # mcrs-eval's sweeps too are checked job by job before the first starts
    ("mcrs.evaluate", "-m", "episodes=1,0"): "mcrs-eval: error: invalid config of sweep job 1 of 2 (episodes=0): episodes=0: must be >= 1; no job was started",
    ("mcrs.evaluate", "-m", "env.comm_range=1,-1"): "mcrs-eval: error: invalid config of sweep job 1 of 2 (env.comm_range=-1): invalid environment config: comm_range=-1.0: must be a distance >= 0",
    ("mcrs.evaluate", "-m", "policy=greedy,gredy"): "mcrs-eval: error: invalid config of sweep job 1 of 2 (policy=gredy): unknown policy 'gredy'; allowed: greedy,",
}  # fmt: skip


#: One refusal per command runs as a real process (the exit status and the stderr a user sees); the rest
#: call the same console entry in this process, which is where the message and the clean-up are decided.
AS_PROCESSES = [
    ("mcrs.train", "env.comm_rage=3"),
    ("mcrs.evaluate", "episodes=0"),
    ("mcrs.render_episode", "uav=9"),
]
COMMANDS = {"mcrs.train": "mcrs-train", "mcrs.evaluate": "mcrs-eval", "mcrs.render_episode": "mcrs-render"}


def _check_refusal(key: tuple[str, ...], err: str, cwd: Path) -> None:
    assert err.startswith(REFUSED[key]), (key, err)
    if "invalid config:\n" not in err:  # validation lists every problem, one line each
        assert err.count("\n") == 1, (key, err)
    assert not any(noise in err for noise in HYDRA_NOISE), (key, err)
    assert list(cwd.iterdir()) == [], (key, sorted(map(str, cwd.rglob("*"))))


@pytest.mark.slow
def test_refused_commands_print_one_line_of_ours_and_leave_no_directory(tmp_path: Path) -> None:
    """Each command starts in an empty directory of its own (at once: they only wait for their imports);
    afterwards that directory is still empty: no ``outputs/<map>/<algo>/``."""
    procs = {}
    for n, (module, *args) in enumerate(AS_PROCESSES):
        (tmp_path / str(n)).mkdir()
        procs[(module, *args)] = (tmp_path / str(n), _start(module, tmp_path / str(n), *args))
    for key, (cwd, proc) in procs.items():
        out, err = proc.communicate(timeout=300)
        assert proc.returncode == 1, (key, out, err)
        _check_refusal(key, err, cwd)


@pytest.mark.parametrize("key", [key for key in REFUSED if key not in AS_PROCESSES], ids=" ".join)
def test_refused_command_in_process_is_one_line_and_leaves_no_directory(
    key: tuple[str, ...], tmp_path: Path, monkeypatch, capsys
) -> None:
    """The console entry raises ``SystemExit(<one line>)``, which the interpreter prints to stderr with
    exit status 1; nothing else is printed, and no ``outputs/`` (nor ``outputs/multirun/``) is left."""
    module, *args = key
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HYDRA_FULL_ERROR", "0")
    monkeypatch.setattr(sys, "argv", [COMMANDS[module], *args])
    with pytest.raises(SystemExit) as refused:
        importlib.import_module(module).main()
    err = capsys.readouterr().err
    assert isinstance(refused.value.code, str), refused.value.code  # a string: exit status 1
    assert err == "", err
    _check_refusal(key, refused.value.code + "\n", tmp_path)


#: A refusal whose output folder is one the user already had: ``out=`` for mcrs-render, the run directory
#: for the others.
INTO_OWN_FOLDER = [
    ("mcrs.render_episode", "out={folder}", "uav=9"),
    ("mcrs.evaluate", "hydra.run.dir={folder}", "episodes=0"),
    ("mcrs.evaluate", "hydra.run.dir={folder}", "policy=gredy"),
    ("mcrs.train", "hydra.run.dir={folder}", "train.lr=-1"),
]


@pytest.mark.parametrize("key", INTO_OWN_FOLDER, ids=" ".join)
@pytest.mark.parametrize("holds", ["nothing", "a log of one's own"])
def test_a_refused_command_leaves_a_folder_that_was_there_before_it(
    key: tuple[str, ...], holds: str, tmp_path: Path, monkeypatch
) -> None:
    """Only what the refused command made is removed: a folder of one's own (empty, or holding only files
    that look like Hydra's, a ``*.log``) stays, with every file that was in it."""
    module, *args = key
    folder = tmp_path / "mine"
    folder.mkdir()
    if holds != "nothing":
        (folder / "server.log").write_text("precious\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HYDRA_FULL_ERROR", "0")
    monkeypatch.setattr(sys, "argv", [COMMANDS[module], *(a.format(folder=folder) for a in args)])
    with pytest.raises(SystemExit) as refused:
        importlib.import_module(module).main()
    assert isinstance(refused.value.code, str) and "error" in refused.value.code, refused.value.code
    assert folder.is_dir()
    if holds != "nothing":
        assert (folder / "server.log").read_text() == "precious\n"


@pytest.mark.slow
def test_hydra_full_error_still_gives_hydras_trace(tmp_path: Path) -> None:
    """A user who asks Hydra for its full trace (``HYDRA_FULL_ERROR=1``) still gets it."""
    done = subprocess.run(
        [sys.executable, "-m", "mcrs.train", "env.comm_rage=3"],
        cwd=tmp_path,
        env={**os.environ, "HYDRA_FULL_ERROR": "1", "PYTHONPATH": str(Path.cwd())},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 1 and "Traceback" in done.stderr and "ConfigCompositionException" in done.stderr


# ------------------------------------------------------------------------ refused before the stack loads
_REFUSE_IN_PROCESS = """
import sys, runpy
sys.argv = ["mcrs-train", *sys.argv[1:]]
try:
    runpy.run_module("mcrs.train", run_name="__main__")
except SystemExit as stop:
    print(stop.code, file=sys.stderr)
print(sorted(m for m in ("torch", "torchrl", "tensordict") if m in sys.modules))
"""


@pytest.mark.parametrize(
    ("overrides", "expected"),
    [
        (["env.comm_rage=3"], "env.comm_rage: unknown key"),
        (["train.lr=-1", "model.hidden_dim=0"], "train.lr=-1.0: must be > 0"),
        (
            ["train.total_env_steps=4000", "train.eval_interval=800"],
            "train.total_env_steps=4000: not a whole number of collector batches of 1600 env steps "
            "(train.num_envs=32 x env.max_steps=50); the nearest exact values: 3200 or 4800",
        ),
    ],
    ids=["mistyped_key", "bad_values", "inexact_budget"],
)
def test_a_refused_command_is_refused_before_torch_loads(
    overrides: list[str], expected: str, tmp_path: Path
) -> None:
    """A refusal costs the config's composition and checks, not the import of torch, TorchRL and the
    learners (about 13 s on a loaded 2-core machine): no torch module is loaded, and no directory is left."""
    done = subprocess.run([sys.executable, "-c", _REFUSE_IN_PROCESS, *overrides], cwd=tmp_path,
                          capture_output=True, text=True, timeout=120,
                          env={**os.environ, "HYDRA_FULL_ERROR": "0"})  # fmt: skip
    assert expected in done.stderr, done.stderr
    assert done.stdout.strip() == "[]", done.stdout  # neither torch, TorchRL nor tensordict was imported
    assert "Traceback" not in done.stderr and not (tmp_path / "outputs").exists()


def test_whole_batch_errors_name_the_nearest_whole_batches() -> None:
    from mcrs.experiment.training.whole_batches import collector_batch, whole_batch_errors

    cfg = compose_config("train.total_env_steps=4000", "train.eval_interval=800", tiny=False)
    assert collector_batch(cfg) == 1600  # 32 envs x 50 steps (map10, the pymarl preset)
    explicit = {"train.total_env_steps", "train.eval_interval"}
    total, interval = whole_batch_errors(cfg, explicit)
    assert total.endswith("the nearest exact values: 3200 or 4800") and "\n" not in total
    assert interval.startswith("train.eval_interval=800:") and interval.endswith("values: 1600")
    assert whole_batch_errors(cfg, set()) == []  # a preset's values are not the command line's
    exact = compose_config("train.total_env_steps=4800", "train.eval_interval=1600", tiny=False)
    assert whole_batch_errors(exact, explicit) == []
    map20 = compose_config("env=map20", "train.num_envs=8", "train.total_env_steps=4000", tiny=False)
    assert whole_batch_errors(map20, {"train.total_env_steps"}) == []  # 8 x 100 = 800: 4000 is five batches


@pytest.mark.parametrize(
    ("module", "listed", "not_listed"),
    [
        (
            "mcrs.train",
            ["algo", "budget", "env", "experiment", "logger", "model", "preset", "task"],
            ["study"],
        ),
        ("mcrs.evaluate", ["env", "study"], ["algo", "budget", "experiment", "logger", "model", "preset"]),
    ],
)
def test_help_lists_only_the_groups_the_command_accepts(
    module: str, listed: list[str], not_listed: list[str], tmp_path: Path
) -> None:
    """The three commands share one config folder; each ``--help`` lists the groups of its own defaults
    (``mcrs-train --help`` listed mcrs-eval's ``study``, which mcrs-train refuses). mcrs-eval loads torch
    before Hydra starts: a generous timeout for a loaded machine."""
    done = subprocess.run([sys.executable, "-m", module, "--help"], cwd=tmp_path, capture_output=True,
                          text=True, timeout=600, env={**os.environ, "HYDRA_FULL_ERROR": "0"})  # fmt: skip
    assert done.returncode == 0, done.stderr
    groups = done.stdout.split("== Configuration groups ==", 1)[1].split("== Config ==", 1)[0]
    named = {line.split(":", 1)[0] for line in groups.splitlines() if ": " in line}
    assert named == set(listed), groups
    assert not any(f"\n{group}: " in groups for group in not_listed), groups
    assert "study" not in done.stdout if module == "mcrs.train" else "study: comm_range, heuristics" in groups
    assert list(tmp_path.iterdir()) == []  # --help runs nothing


def test_a_task_key_without_a_task_is_one_line_naming_the_tasks() -> None:
    """``+task._target_=...`` with no ``task=`` used to end in OmegaConf's bare AssertionError."""
    from mcrs.experiment.commands.cli import command_line_problems

    (problem,) = command_line_problems(["+task._target_=os.system"], tasks=True)
    assert problem.startswith(
        "task._target_: no task is chosen: pick one first with task=<name> (simple_spread,"
    )
    assert command_line_problems(["task=simple_spread", "task.max_steps=5"], tasks=True) == []
    assert command_line_problems(["+task._target_=os.system"]) == []  # a command without tasks says its own
    done = subprocess.run(
        [sys.executable, "-m", "mcrs.train", "task.max_steps=5"], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 1 and done.stderr.strip().splitlines() == [
        "mcrs-train: error: task.max_steps: no task is chosen: pick one first with task=<name> (simple_spread, "
        'vmas_navigation), or pass a Task object in Python (docs/API.md, "Bring your own task")'
    ]
