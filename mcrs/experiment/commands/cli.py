"""What the Hydra command lines share: a refused command is one line of ours and leaves no directory.

Hydra reports a misspelt key or an unknown option with a page of internals; :func:`one_line_errors` wraps a
``@hydra.main`` entry point so that each composition error is one line naming the key and what is allowed
(:func:`~mcrs.experiment.util.messages.describe`). :class:`RunDirCheck`, a Hydra callback, creates the run or
sweep directory before Hydra does, refusing an unwritable one, and remembers what it made so that
:func:`remove_refused_dirs` can remove it when the command is refused.
"""

from __future__ import annotations

import functools
import os
import shutil
import sys
from collections.abc import Callable, Collection, Sequence
from pathlib import Path
from typing import Any, TypeVar

from hydra import compose
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import Override, OverrideType
from hydra.errors import HydraException
from hydra.experimental.callback import Callback
from hydra.utils import get_method
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from mcrs.experiment.commands.sweep import sweep_jobs
from mcrs.experiment.run.rundir import (
    LOCK,
    RunDirError,
    claim_run_dir,
    describe_os_error,
    fresh_problem,
    in_use_problem,
    release_claims,
    resume_problem,
)
from mcrs.experiment.schema import CONFIG_DIR
from mcrs.experiment.util.messages import GRAMMAR, describe
from mcrs.experiment.util.untrusted import PLAIN_NAME

F = TypeVar("F", bound=Callable[..., Any])
#: Files Hydra and the sweep's progress write into a run or sweep directory before the task runs.
HYDRA_FILES = (".hydra", "multirun.yaml", ".sweep")


def one_line_errors(command: str, interrupted: str | None = None) -> Callable[[F], F]:
    """Wrap a ``@hydra.main`` function so that a composition error exits with ``<command>: error: <one line>``
    and removes the directories the command made. With ``interrupted``, Ctrl-C prints ``<command>: SIGINT:
    <interrupted>`` and exits 130. Overrides of Hydra's own config are judged before Hydra starts, since a
    callback would run before any check. ``HYDRA_FULL_ERROR=1`` is set for the call so that Hydra re-raises.
    """

    def wrap(hydra_main: F) -> F:
        @functools.wraps(hydra_main)
        def entry(*args: Any, **kwargs: Any) -> Any:
            refused = command_line_problems(sys.argv[1:], tasks=command == "mcrs-train")
            if refused:  # before Hydra instantiates a callback or writes anything
                raise SystemExit(f"{command}: error: {refused[0]}")
            if os.environ.get("HYDRA_FULL_ERROR") == "1":
                return hydra_main(*args, **kwargs)
            before = os.environ.get("HYDRA_FULL_ERROR")
            os.environ["HYDRA_FULL_ERROR"] = "1"
            try:
                return hydra_main(*args, **kwargs)
            except (HydraException, OmegaConfBaseException) as error:
                remove_refused_dirs()
                raise SystemExit(f"{command}: error: {describe(error)}") from None
            except KeyboardInterrupt:
                if interrupted is None:
                    raise
                remove_refused_dirs()
                print(f"{command}: SIGINT: {interrupted}", flush=True)
                raise SystemExit(130) from None
            finally:
                if before is None:
                    os.environ.pop("HYDRA_FULL_ERROR", None)
                else:
                    os.environ["HYDRA_FULL_ERROR"] = before

        return entry  # type: ignore[return-value]

    return wrap


# ------------------------------------------------------------------------------ overrides of Hydra
#: Logging settings a command line may change: levels, not where or through what the records go.
LOGGING_KEYS = {"level", "propagate", "disable_existing_loggers"}


def _under(key: str, node: str) -> bool:
    return key == node or key.startswith(node + ".")


def _parsed(overrides: Sequence[str]) -> list[Override]:
    """The overrides Hydra's grammar reads; one it cannot read is left for Hydra to report."""
    parser, out = OverridesParser.create(), []
    for text in overrides:
        try:
            out.append(parser.parse_override(text))
        except (HydraException, ValueError):
            continue
    return out


def _inside_path(value: object) -> bool:
    """Whether ``value`` is a path that stays inside the folder it is joined to: relative, no ``..``, ``~`` or
    ``${``."""
    if not isinstance(value, str) or not value or "${" in value or value.startswith("~"):
        return False
    path = Path(value)
    return not path.is_absolute() and ".." not in path.parts


def hydra_override_problem(override: Override) -> str | None:
    """What is wrong with a command-line override of Hydra's own config: a callback, which Hydra runs before
    any check, a log handler, or Hydra's files or log moved out of the run directory. The run directory,
    launcher, sweeper and log levels stay free."""
    key, text = override.key_or_group, override.input_line or override.key_or_group
    if "hydra" in str(override.package or "").split("."):
        return f"{text}: a config placed into Hydra's own settings: refused"
    if key == "hydra" or _under(key, "hydra.callbacks"):
        return (
            f"{text}: adds, changes or removes a Hydra callback, code Hydra runs before the command checks "
            "anything: refused (the command's own callbacks are fixed)"
        )
    for node in ("hydra.job_logging", "hydra.hydra_logging"):
        group = key == node.replace(".", "/")  # hydra/job_logging=default: another set of handlers
        if group or (_under(key, node) and key.rsplit(".", 1)[-1] not in LOGGING_KEYS):
            return (
                f"{text}: the command's log is written in its run directory through its own handlers; "
                f"only levels may be set ({node}.root.level=WARNING)"
            )
    if key == "hydra.output_subdir" and override.type != OverrideType.DEL:
        value = None if override.is_sweep_override() else override.value()
        if override.is_sweep_override() or (value is not None and not _inside_path(value)):
            return (
                f"{text}: Hydra's files go in a folder inside the run directory: a relative path without "
                "'..', '~' or '${...}' (.hydra), or null for none"
            )
    if key == "hydra.job.name":
        value = None if override.is_sweep_override() else override.value()
        if not isinstance(value, str) or not PLAIN_NAME.fullmatch(value):
            return f"{text}: the job's name names its log file in the run directory: a plain name (letters, digits, _ . + = -)"
    return None


def command_line_problems(argv: Sequence[str], tasks: bool = False) -> list[str]:
    """The overrides of a command line that :func:`hydra_override_problem` refuses and, when the command takes
    ``task=`` (``tasks``), a task key set with no task chosen, one line each."""
    texts = [a for a in argv if ("=" in a or a.startswith("~")) and not a.startswith("-")]
    problems = [p for p in map(hydra_override_problem, _parsed(texts)) if p]
    return problems + (_unchosen_task(texts) if tasks else [])


def _unchosen_task(texts: Sequence[str]) -> list[str]:
    """``task.<key>=...`` without ``task=<name>``, which OmegaConf would refuse with an AssertionError that
    names nothing."""
    keys = [t.split("=", 1)[0] for t in texts]
    if any(k.lstrip("+~") == "task" for k in keys):
        return []
    setting = next((k for k in keys if k.lstrip("+~").startswith("task.")), None)
    if setting is None:
        return []
    options = sorted(p.stem for p in (Path(CONFIG_DIR) / "task").glob("*.yaml"))
    return [
        f"{setting.lstrip('+~')}: no task is chosen: pick one first with task=<name> ({', '.join(options)}), "
        'or pass a Task object in Python (docs/API.md, "Bring your own task")'
    ]


def _strings(value: object) -> list[str]:
    if isinstance(value, dict):
        return [s for k, v in value.items() for s in (*_strings(k), *_strings(v))]
    if isinstance(value, (list, tuple)):
        return [s for v in value for s in _strings(v)]
    return [value] if isinstance(value, str) else []


def file_override_problem(text: object, reserved: Collection[str]) -> str | None:
    """What is wrong with an override read from a file someone else wrote, such as a campaign file, which sets
    config values only: no Hydra setting, no ``resume``/``overwrite`` or ``reserved`` key, no interpolation
    and no path."""
    if not isinstance(text, str):
        return f"{text!r}: an override is a string key=value"
    parsed = _parsed([text])
    if not parsed:
        return f"{text!r}: not an override key=value (the syntax: {GRAMMAR})"
    override = parsed[0]
    key = override.key_or_group
    root = key.replace("/", ".").split(".", 1)[0]
    if root == "hydra" or "hydra" in str(override.package or "").split("."):
        return (
            f"{text}: a Hydra setting (callbacks, output and log folders): a campaign file sets config values "
            "only; where the runs and their files go is the campaign's"
        )
    if key in {"resume", "overwrite", *reserved}:
        allowed = ", ".join(sorted({"resume", "overwrite", *reserved}))
        return f"{text}: set by the tool for each run ({allowed}): not in a campaign file"
    value = None if override.is_sweep_override() else override.value()
    if override.is_sweep_override():
        return f"{text}: a sweep of values: a campaign file sets one value per override"
    for string in _strings(value):
        if "${" in string:
            return f"{text}: an interpolation (${{...}}): a campaign file sets plain values"
        if "/" in string or "\\" in string or string.startswith("~") or string == "..":
            return f"{text}: {string!r} names a path: a campaign file sets config values, not paths"
    return None


# --------------------------------------------------------------------------------- run directories
#: (directory, the topmost directory this process created for it), in the order they were made.
_CREATED: list[tuple[Path, Path]] = []


class RunDirCheck(Callback):
    """A Hydra callback that creates the run or sweep directory before Hydra does and checks that it can be
    written, so that a bad path is one line; what it makes is remembered for :func:`remove_refused_dirs`."""

    def __init__(self, command: str = "mcrs", fresh_run: bool = False, validate: str | None = None) -> None:
        self.command = command
        self.fresh_run = fresh_run  # mcrs-train: the directory of a fresh run is checked as Experiment does
        # mcrs-train's early check (mcrs.train.early_errors), named because it sits above this package
        self.validate = validate

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        resume = OmegaConf.select(config, "resume", default=None)  # mcrs-train's resume=<run>
        problem = resume_problem(resume) if resume is not None else None
        run_dir = Path(str(config.hydra.run.dir))
        if problem is None and resume is not None:
            problem = in_use_problem(Path(str(resume)).expanduser())
        elif problem is None and self.fresh_run:  # before Hydra writes .hydra/ and the log into a run
            overwrite = bool(OmegaConf.select(config, "overwrite", default=False))
            problem = (
                in_use_problem(run_dir) or fresh_problem(run_dir, overwrite) or self._invalid(config, run_dir)
            )
        if problem:  # the run directory would be the one named: refused before anything is made
            raise SystemExit(f"{self.command}: error: {problem}")
        self._make(run_dir)
        if self.fresh_run:  # mcrs-train: the run is this process's before Hydra writes .hydra/ or the log
            try:
                claim_run_dir(Path(str(resume)).expanduser() if resume is not None else run_dir)
            except RunDirError as error:
                remove_refused_dirs()
                raise SystemExit(f"{self.command}: error: {error}") from None

    def _invalid(self, config: DictConfig, run_dir: Path) -> str | None:
        """The refusal of a config the command will refuse, judged before Hydra rewrites the ``.hydra/`` files
        of a run already in ``run_dir``."""
        if self.validate is None or not (run_dir.is_dir() and any(run_dir.iterdir())):
            return None
        job_config = OmegaConf.masked_copy(config, [key for key in config if key != "hydra"])
        problems = get_method(self.validate)(job_config, list(config.hydra.overrides.task))
        if not problems:
            return None
        return "invalid config: " + (
            problems[0] if len(problems) == 1 else "\n  - " + "\n  - ".join(problems)
        )

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        problem = self._invalid_job(config)
        if problem:  # a sweep that would fail at its k-th job after hours of the others: refused now
            raise SystemExit(f"{self.command}: error: {problem}")
        self._make(Path(str(config.hydra.sweep.dir)))

    def _invalid_job(self, config: DictConfig) -> str | None:
        """The first sweep job whose config the command will refuse, composed as the job will be; a job that
        does not compose reports that itself."""
        jobs = sweep_jobs(config) if self.validate is not None else None
        if not jobs:
            return None
        check, name = get_method(self.validate), str(config.hydra.job.config_name)
        shared = set.intersection(*(set(job) for job in jobs))
        for num, overrides in enumerate(jobs):
            try:
                job_config = compose(config_name=name, overrides=overrides)
            except Exception:  # Hydra's composition errors: the job reports its own
                continue
            problems = check(job_config, overrides)
            if problems:
                swept = " ".join(o for o in overrides if o not in shared)
                more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
                return (
                    f"invalid config of sweep job {num} of {len(jobs)} ({swept}): {problems[0]}{more}; "
                    "no job was started"
                )
        return None

    def _make(self, directory: Path) -> None:
        try:
            make_run_dir(directory)
            probe = directory / f".mcrs-write-test.{os.getpid()}"
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as error:
            remove_refused_dirs()
            raise SystemExit(
                f"{self.command}: error: cannot write the run directory {directory}: {describe_os_error(error)}"
            ) from None


def make_run_dir(directory: Path) -> None:
    """``mkdir -p``, remembering the topmost directory that did not exist."""
    directory = Path(os.path.abspath(directory))
    missing = [p for p in (directory, *directory.parents) if not p.exists()]
    directory.mkdir(parents=True, exist_ok=True)
    if missing:
        _CREATED.append((directory, missing[-1]))


def remove_refused_dirs(run_dir: Path | None = None) -> None:
    """Remove what a refused command made: each directory :class:`RunDirCheck` made, and ``run_dir`` inside
    one of them, when it holds only Hydra's files, then the empty parents this process created. Directories
    that existed before, or hold a lock or other files, stay."""
    release_claims()
    if run_dir is not None:
        run_dir = Path(os.path.abspath(run_dir))
        if any(run_dir.is_relative_to(root) for _, root in _CREATED):
            _remove_if_unused(run_dir)
    for directory, root in reversed(_CREATED):
        _remove_if_unused(directory)
        for parent in (directory, *directory.parents):
            if not parent.is_relative_to(root):
                break
            if not parent.exists():
                continue
            try:
                parent.rmdir()  # only an empty one
            except OSError:
                break
    _CREATED.clear()


def _remove_if_unused(directory: Path) -> None:
    try:
        entries = list(directory.iterdir())
    except OSError:
        return
    if all(_hydra_file(p) for p in entries):
        shutil.rmtree(directory, ignore_errors=True)


def _hydra_file(path: Path) -> bool:
    """What Hydra writes before the task runs: ``.hydra/``, ``multirun.yaml``, the job's ``<name>.log``."""
    if path.name == LOCK:
        return False
    return path.name in HYDRA_FILES or (path.suffix == ".log" and path.is_file())
