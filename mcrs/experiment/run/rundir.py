"""A run directory belongs to one run: unique names, one writer at a time, no mixing with an old run.

:class:`RunLock` is an exclusive ``flock`` on ``<run>/.mcrs.lock``. The kernel drops it when its process dies,
even by SIGKILL, so a crashed run can be resumed at once while a second writer is refused.
:func:`prepare_fresh` refuses a non-empty directory unless ``overwrite=true``, and then clears only what a run
writes. :func:`fingerprint` says what a checkpoint must share with the run it resumes.
"""

from __future__ import annotations

import contextlib
import csv
import fcntl
import logging
import os
import shutil
import socket
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

# omegaconf and hydra are imported where used: this module needs only the standard library.

LOCK = ".mcrs.lock"
#: What ``mcrs-train`` writes into a run directory, with ``mcrs-eval``'s and ``mcrs-render``'s results of
#: the run (``overwrite=true`` removes exactly these).
RUN_ARTEFACTS = ("config.yaml", "checkpoints", "logs", "wandb", "videos", "report", "eval", "render")
#: What a run directory must hold to be resumed (:func:`mcrs.experiment.run.checkpoint.checkpoint_path`).
LAST_CHECKPOINT = "checkpoints/last.pt"
#: What may be in a fresh run directory before the run writes: Hydra's own files and our lock.
FRESH_ALLOWED = (".hydra", LOCK)


class RunDirError(RuntimeError):
    """A run directory that this process may not write (in use, holding another run, unwritable)."""


def register_resolvers() -> None:
    """Register the ``${mcrs.*:}`` resolvers of the configs' run-directory names and ``--help`` texts.
    ``${mcrs.pid:}`` is cached like ``${now:}``, so a sweep's jobs share the launcher's value and two commands
    started in one second get different directories."""
    from omegaconf import OmegaConf

    if not OmegaConf.has_resolver("mcrs.pid"):
        OmegaConf.register_new_resolver("mcrs.pid", lambda: str(os.getpid()), use_cache=True)
    if not OmegaConf.has_resolver("mcrs.num"):  # ``rc${mcrs.num:${env.comm_range}}``: rc5, not rc5.0
        OmegaConf.register_new_resolver("mcrs.num", lambda value: f"{float(value):g}")
    if not OmegaConf.has_resolver("mcrs.run_dir"):
        OmegaConf.register_new_resolver("mcrs.run_dir", resumed_run_dir)
    if not OmegaConf.has_resolver("mcrs.resuming"):
        OmegaConf.register_new_resolver(
            "mcrs.resuming", lambda resume, fresh, resumed: fresh if resume in (None, "") else resumed
        )
    if not OmegaConf.has_resolver("mcrs.beside_run"):
        OmegaConf.register_new_resolver("mcrs.beside_run", beside_run)
    if not OmegaConf.has_resolver("mcrs.task_name"):  # outputs/<task or map>/...: the task's name
        OmegaConf.register_new_resolver("mcrs.task_name", task_name)
    if not OmegaConf.has_resolver("mcrs.config_groups"):  # --help: the groups the command accepts
        OmegaConf.register_new_resolver("mcrs.config_groups", config_groups_help)


def task_name(task: Any, env_name: str) -> str:
    """The task part of a run directory's name: the task's ``name`` or class, or the map for an MCRS run."""
    if task is None:
        return str(env_name)
    name = task.get("name") if hasattr(task, "get") else None
    return str(name or str(task.get("_target_", "task")).rsplit(".", 1)[-1])


def config_groups_help(*, _root_: Any) -> str:
    """The config groups a command accepts, one ``group: option, option`` line each, for its ``--help``.
    Hydra's ``$APP_CONFIG_GROUPS`` lists every group of the shared config folder, even another command's."""
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.object_type import ObjectType
    from omegaconf import OmegaConf

    choices = OmegaConf.select(_root_, "hydra.runtime.choices", default=None) or {}
    groups = sorted(str(g) for g in choices if not str(g).startswith("hydra/") and str(g) != "hydra")
    hydra = GlobalHydra.instance().hydra if GlobalHydra.instance().is_initialized() else None
    lines = []
    for group in groups:
        if hydra is not None:
            options = hydra.config_loader.get_group_options(group, ObjectType.CONFIG)
        else:  # not under Hydra: the packaged config folder
            options = [p.stem for p in (Path(__file__).resolve().parents[1] / "conf" / group).glob("*.yaml")]
        lines.append(f"{group}: {', '.join(sorted(options))}")
    return "\n".join(lines) + "\n"


def resumed_run_dir(resume: Any, fresh: str) -> str:
    """``hydra.run.dir`` of ``mcrs-train``: the run being resumed, else ``fresh``, a new run's name."""
    return fresh if resume in (None, "") else str(Path(str(resume)).expanduser())


def resume_problem(resume: Any) -> str | None:
    """Why ``resume=<dir>`` cannot be resumed, or None; checked before Hydra makes or writes anything."""
    run_dir = Path(str(resume)).expanduser()
    if not run_dir.is_dir():
        return f"resume={resume}: no such directory"
    if not (run_dir / "config.yaml").is_file() or not (run_dir / LAST_CHECKPOINT).is_file():
        return f"resume={resume}: not an mcrs-train run directory (needs config.yaml and {LAST_CHECKPOINT})"
    return None


def run_of(policy: Any) -> Path | None:
    """The ``mcrs-train`` run that ``policy`` names (the run or a checkpoint in it), or None."""
    path = Path(str(policy)).expanduser()
    candidates = (
        (path.parent.parent,) if path.suffix == ".pt" and path.parent.name == "checkpoints" else (path,)
    )
    for run in candidates:
        if (run / "config.yaml").is_file() and (run / "checkpoints").is_dir():
            return run
    return None


def beside_run(policy: Any, kind: str, default: str) -> str:
    """Where ``mcrs-eval`` and ``mcrs-render`` write: ``<run>/<kind>`` for a trained run's policy, else
    ``default``."""
    run = run_of(policy)
    return str(run / kind) if run is not None else default


#: Run directories this process claimed before Hydra wrote into them (:func:`claim_run_dir`), by their
#: resolved path: the lock and whether this process created the lock file.
_CLAIMED: dict[Path, tuple[RunLock, bool]] = {}


def _key(run_dir: str | Path) -> Path:
    return Path(os.path.abspath(run_dir)).resolve()


def claim_run_dir(run_dir: str | Path) -> None:
    """Take ``run_dir``'s lock before Hydra writes there, so a second command started into it is refused
    before it writes anything. This process's :class:`RunLock` takes the claim over."""
    key = _key(run_dir)
    if key in _CLAIMED:
        return
    existed = (key / LOCK).exists()
    _CLAIMED[key] = (RunLock(run_dir), not existed)


def claimed(run_dir: str | Path) -> bool:
    """Whether this process claimed ``run_dir`` and no lock has taken the claim over yet."""
    return _key(run_dir) in _CLAIMED


def release_claims() -> None:
    """Drop the claims of a command refused before its run started, with any lock file a claim created."""
    for key, (lock, created) in list(_CLAIMED.items()):
        if created and lock.fd is not None:
            (key / LOCK).unlink(missing_ok=True)  # while still held: no other process relies on it
        lock.release()
    _CLAIMED.clear()


class RunLock:
    """An exclusive advisory lock on a run directory, held until :meth:`release` or process exit."""

    def __init__(self, run_dir: str | Path) -> None:
        self.fd: int | None = None
        self.path = Path(run_dir) / LOCK
        claimed = _CLAIMED.pop(_key(run_dir), None)
        if claimed is not None and claimed[0].fd is not None:  # this process's claim: taken over
            self.fd, claimed[0].fd = claimed[0].fd, None
            return
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as error:
            raise RunDirError(
                f"cannot write the run directory {Path(run_dir)}: {describe_os_error(error)}"
            ) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 200, 0).decode(errors="replace").split()
            os.close(fd)
            pid = holder[0] if holder else "unknown"
            host = f" on {holder[1]}" if len(holder) > 1 and holder[1] != socket.gethostname() else ""
            raise RunDirError(
                f"run directory {Path(run_dir)} is in use by process {pid}{host}: one process writes a run; "
                "wait for it to end (then resume=), or choose another directory"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()} {socket.gethostname()}\n".encode(), 0)
        self.fd = fd

    def release(self) -> None:
        """Drop the lock; the file stays, it holds no state."""
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None

    def __del__(self) -> None:
        self.release()


def lock_holder(run_dir: str | Path) -> str | None:
    """``"process 7438"`` when a live process holds ``run_dir``'s lock, else None; creates nothing."""
    try:
        fd = os.open(Path(run_dir) / LOCK, os.O_RDWR)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.pread(fd, 200, 0).decode(errors="replace").split()
        return f"process {holder[0] if holder else 'unknown'}"
    finally:
        os.close(fd)  # closing drops a lock taken here
    return None


def in_use_problem(run_dir: Path) -> str | None:
    """The refusal :class:`RunLock` would give, said before anything is written."""
    holder = lock_holder(run_dir)
    if holder is None:
        return None
    return (
        f"run directory {run_dir} is in use by {holder}: one process writes a run; "
        "wait for it to end (then resume=), or choose another directory"
    )


class RunLogHandler(logging.FileHandler):
    """The file handler of ``mcrs-train``'s log, which claims a sweep job's directory before Hydra writes
    there. A job whose folder is in use or holds another run stops the sweep, which would otherwise leave a
    hole its summary hides."""

    def __init__(self, filename: str, overwrite: bool = False, **kwargs: Any) -> None:
        run_dir = Path(filename).parent
        if not claimed(run_dir):
            try:
                problem = in_use_problem(run_dir) or fresh_problem(run_dir, bool(overwrite))
                if problem is None:
                    claim_run_dir(run_dir)
            except RunDirError as error:  # taken meanwhile, or not writable
                problem = str(error)
            except OSError as error:
                problem = f"cannot read the run directory {run_dir}: {describe_os_error(error)}"
            if problem:
                release_claims()
                raise SystemExit(f"mcrs-train: error: {_sweep_job_refused(problem)}")
        super().__init__(filename, **kwargs)


def _sweep_job_refused(problem: str) -> str:
    """``sweep job 3: <problem>; the sweep stops: ...`` for a sweep's job, else ``problem``."""
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import OmegaConf

    num = OmegaConf.select(HydraConfig.get(), "job.num", default=None) if HydraConfig.initialized() else None
    if num is None:
        return problem
    return f"sweep job {num}: {problem}; the sweep stops: no later job was started"


def _fresh_entries(run_dir: Path) -> list[str]:
    return sorted(p.name for p in run_dir.iterdir() if p.name not in FRESH_ALLOWED and not _hydra_log(p))


def fresh_problem(run_dir: Path, overwrite: bool) -> str | None:
    """Why a fresh run may not start in ``run_dir``, or None; asked before Hydra writes there."""
    if not run_dir.is_dir():
        return None
    entries = _fresh_entries(run_dir)
    if not entries:
        return None
    shown = ", ".join(entries[:5]) + (", ..." if len(entries) > 5 else "")
    if not overwrite:
        return (
            f"run directory {run_dir} is not empty ({shown}): resume it with resume={run_dir}, "
            "choose another hydra.run.dir, or pass overwrite=true to replace the run in it (in Python: "
            "Experiment(config, run_dir, resume=True), another run_dir, or config.overwrite = True)"
        )
    foreign = [name for name in entries if name not in RUN_ARTEFACTS]
    if foreign:
        return (
            f"run directory {run_dir} holds files that no run wrote ({', '.join(foreign[:5])}): "
            "overwrite=true only replaces a previous run; choose another hydra.run.dir"
        )
    return None


def prepare_fresh(run_dir: Path, overwrite: bool) -> None:
    """Refuse a run directory that holds anything but Hydra's files, or clear a previous run's own files
    (:data:`RUN_ARTEFACTS`) from it."""
    problem = fresh_problem(run_dir, overwrite)
    if problem:
        raise RunDirError(problem)
    for name in _fresh_entries(run_dir):
        path = run_dir / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()


def _hydra_log(path: Path) -> bool:
    """Hydra's job log (``<job name>.log``), written before the task starts."""
    return path.suffix == ".log" and path.is_file()


def csv_log_files(run_dir: Path) -> list[Path]:
    return sorted((run_dir / "logs" / "scalars").rglob("*.csv"))


def csv_log_name(run_dir: Path, path: Path) -> str:
    """``train/episodes`` for ``<run>/logs/scalars/train/episodes.csv``."""
    return path.relative_to(run_dir / "logs" / "scalars").with_suffix("").as_posix()


def truncate_csv_logs(run_dir: Path, rows: Mapping[str, int] | None, env_steps: int) -> dict[str, int]:
    """Keep the rows each CSV log had when the checkpoint was written (``rows``, name -> count), rewriting
    each file atomically. Without ``rows`` the rows up to ``env_steps`` stay (history.OLD_FORMS["no
    logs.rows"])."""
    kept: dict[str, int] = dict(rows or {})
    for path in csv_log_files(run_dir):
        with open(path, newline="") as f:
            lines = [row for row in csv.reader(f) if row]
        if rows is not None:
            keep = lines[: rows.get(csv_log_name(run_dir, path), 0)]
        else:
            keep = [row for row in lines if float(row[0]) <= env_steps]
        kept[csv_log_name(run_dir, path)] = len(keep)
        if len(keep) == len(lines):
            continue
        tmp = path.with_name(f".{path.name}.tmp")
        with open(tmp, "w", newline="") as f:
            csv.writer(f, lineterminator="\n").writerows(keep)
        os.replace(tmp, path)
    return kept


# ---------------------------------------------------------------------------------------- fingerprint
#: The order in which a difference is reported: what identifies a run first, then section by section.
FINGERPRINT_FIRST = (
    "algo.name", "algo.mixer", "algo.memory.enabled", "algo.memory.embedding", "env.name", "env.width",
    "env.height", "env.n_uavs", "env.n_targets", "env.n_no_fly", "env.max_steps", "model.name",
    "model.hidden_dim",
)  # fmt: skip
FINGERPRINT_ORDER = ("algo", "env", "model", "seed", "train", "device", "preset")


def fingerprint(
    config: Mapping[str, Any], networks: Mapping[str, Any], version: int, mutable: Iterable[str]
) -> dict[str, Any]:
    """What a checkpoint must share with the run that resumes it: ``format.version``, the config fields that
    are not ``mutable``, then each learned tensor's shape. Plain values, flat and ordered."""
    mutable = tuple(mutable)

    def is_mutable(name: str) -> bool:
        return any(name == m or name.startswith(m + ".") for m in mutable)

    out: dict[str, Any] = {"format.version": version}
    flat = _flatten(config)
    ordered = sorted(flat, key=lambda k: (_rank(k), k))
    out.update({k: flat[k] for k in ordered if not is_mutable(k)})
    for module, state in networks.items():
        for name, value in state.items():
            if hasattr(value, "shape"):
                out[f"networks.{module}.{name}"] = list(value.shape)
    return out


def _rank(name: str) -> int:
    if name in FINGERPRINT_FIRST:
        return FINGERPRINT_FIRST.index(name) - len(FINGERPRINT_FIRST)
    top = name.split(".", 1)[0]
    return FINGERPRINT_ORDER.index(top) if top in FINGERPRINT_ORDER else len(FINGERPRINT_ORDER)


def _flatten(config: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in config.items():
        if isinstance(value, Mapping):
            out.update(_flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = list(value) if isinstance(value, (list, tuple)) else value
    return out


def first_difference(saved: Mapping[str, Any], current: Mapping[str, Any]) -> str | None:
    """``"algo.name: 'cnn_semu' in the checkpoint, 'qmix' in this run"`` for the first field that differs, or
    None. A config field on one side only is skipped (history.OLD_FORMS["config field on one side only"])."""
    for key in [*current, *(k for k in saved if k not in current)]:
        if (key not in saved or key not in current) and not key.startswith("networks."):
            continue
        theirs, ours = saved.get(key, "<missing>"), current.get(key, "<missing>")
        if theirs != ours:
            return f"{key}: {theirs!r} in the checkpoint, {ours!r} in this run"
    return None


# ---------------------------------------------------------------------------------------- I/O errors
def describe_os_error(error: OSError) -> str:
    """``"No space left on device (/run/checkpoints/x.pt)"``: the reason and the file."""
    reason = error.strerror or str(error) or type(error).__name__
    return f"{reason} ({error.filename})" if error.filename else reason


@contextlib.contextmanager
def io_errors(action: str, after: str | Callable[[], str] = ""):
    """Turn an ``OSError`` in the block into a one-line :class:`RunDirError`. ``after`` says what is still
    intact, or is a function that says it after the error."""
    try:
        yield
    except OSError as error:
        intact = after() if callable(after) else after
        raise RunDirError(f"cannot {action}: {describe_os_error(error)}{intact}") from None
