"""A run directory belongs to one run: unique names, one writer at a time, no mixing with an old run.

- :func:`register_resolvers` adds ``${mcrs.pid:}`` to the run-directory names (``conf/config.yaml``,
  ``conf/eval.yaml``, ``conf/render.yaml``): two commands started in the same second on one machine get
  different directories; ``${mcrs.run_dir:...}`` puts a resumed run back into its own directory and
  ``${mcrs.beside_run:...}`` an evaluation or rendering of a run inside that run's directory.
- :class:`RunLock` is an exclusive ``flock`` on ``<run>/.mcrs.lock``, held by the process that writes the
  run; the kernel drops it when that process dies (even by SIGKILL), so a crashed run can be resumed at
  once, while a second writer or a resume of a live run is refused, naming the holder's PID.
- :class:`RunLogHandler`, the file handler of ``mcrs-train``'s log, claims a sweep job's directory before
  Hydra writes into it (a single run is claimed earlier, by :class:`mcrs.experiment.commands.cli.RunDirCheck`).
- :func:`prepare_fresh` refuses a non-empty directory unless ``overwrite=true``, and then clears only what
  a run writes.
- :func:`truncate_csv_logs` drops the CSV rows written after the checkpoint a run resumes from.
- :func:`fingerprint` and :func:`first_difference`: what a checkpoint must share with the run it resumes.
"""

from __future__ import annotations

import contextlib
import csv
import logging
import os
import shutil
import socket
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

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
    """``${mcrs.pid:}``: this process's id, cached like Hydra's ``${now:}`` so that every job of a sweep
    (which copies the launcher's resolver cache) sees the launcher's value; ``${mcrs.num:x}``: a number as
    directory names write it (5.0 -> 5, 0.13 -> 0.13, inf -> inf); ``${mcrs.config_groups:}``: the config
    groups of a command's ``--help`` (:func:`config_groups_help`)."""
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
    """``${mcrs.task_name:${task},${env.name}}``: a run directory's task part, the task node's ``name`` (else
    its class's name), or the map's name for an MCRS run (``task`` null)."""
    if task is None:
        return str(env_name)
    name = task.get("name") if hasattr(task, "get") else None
    return str(name or str(task.get("_target_", "task")).rsplit(".", 1)[-1])


def config_groups_help(*, _root_: Any) -> str:
    """``${mcrs.config_groups:}`` in a command's ``hydra.help.template``: the config groups that command
    accepts (those of its defaults list, ``hydra.runtime.choices``), one ``group: option, option`` line
    each, as Hydra's ``$APP_CONFIG_GROUPS`` writes them. Hydra's own list names every group in the config
    folder, which ``mcrs-train``, ``mcrs-eval`` and ``mcrs-render`` share: ``mcrs-train --help`` listed
    mcrs-eval's ``study``, which mcrs-train refuses."""
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
    """``hydra.run.dir`` of ``mcrs-train``: the run being resumed (its session appends to its own
    ``train.log``; no stray directory is made), else ``fresh``, the name of a new run."""
    return fresh if resume in (None, "") else str(Path(str(resume)).expanduser())


def resume_problem(resume: Any) -> str | None:
    """Why ``resume=<dir>`` cannot be resumed (not a directory, not an ``mcrs-train`` run), or None.

    Checked before Hydra makes or writes anything (:class:`mcrs.experiment.commands.cli.RunDirCheck`): a mistyped
    path is one line, not a new empty directory."""
    run_dir = Path(str(resume)).expanduser()
    if not run_dir.is_dir():
        return f"resume={resume}: no such directory"
    if not (run_dir / "config.yaml").is_file() or not (run_dir / LAST_CHECKPOINT).is_file():
        return f"resume={resume}: not an mcrs-train run directory (needs config.yaml and {LAST_CHECKPOINT})"
    return None


def run_of(policy: Any) -> Path | None:
    """The ``mcrs-train`` run directory that ``policy`` names (the run itself, or a checkpoint in its
    ``checkpoints/``), or None for a heuristic or a checkpoint outside any run."""
    path = Path(str(policy)).expanduser()
    candidates = (
        (path.parent.parent,) if path.suffix == ".pt" and path.parent.name == "checkpoints" else (path,)
    )
    for run in candidates:
        if (run / "config.yaml").is_file() and (run / "checkpoints").is_dir():
            return run
    return None


def beside_run(policy: Any, kind: str, default: str) -> str:
    """Where ``mcrs-eval`` / ``mcrs-render`` write: ``<run>/<kind>`` when the policy is a trained run's
    (its results stay with the run), else ``default`` (``outputs/eval``, ``outputs/render``)."""
    run = run_of(policy)
    return str(run / kind) if run is not None else default


#: Run directories this process claimed before Hydra wrote into them (:func:`claim_run_dir`), by their
#: resolved path: the lock and whether this process created the lock file.
_CLAIMED: dict[Path, tuple[RunLock, bool]] = {}


def _key(run_dir: str | Path) -> Path:
    return Path(os.path.abspath(run_dir)).resolve()


def claim_run_dir(run_dir: str | Path) -> None:
    """Take ``run_dir``'s lock now, before Hydra writes ``.hydra/`` and the log there: a second command
    started into the same directory (while this one still loads torch) is refused before it writes
    anything. :class:`RunLock` of this process then takes the claim over; :func:`release_claims` drops it
    for a command refused before it ran. Raises :class:`RunDirError` naming the holder."""
    key = _key(run_dir)
    if key in _CLAIMED:
        return
    existed = (key / LOCK).exists()
    _CLAIMED[key] = (RunLock(run_dir), not existed)


def claimed(run_dir: str | Path) -> bool:
    """Whether this process claimed ``run_dir`` (:func:`claim_run_dir`) and no lock has taken it over yet."""
    return _key(run_dir) in _CLAIMED


def release_claims() -> None:
    """Drop the claims of a command refused before its run started; a lock file the claim created goes."""
    for key, (lock, created) in list(_CLAIMED.items()):
        if created and lock.fd is not None:
            (key / LOCK).unlink(missing_ok=True)  # while still held: no other process relies on it
        lock.release()
    _CLAIMED.clear()


class RunLock:
    """An exclusive advisory lock on a run directory, held until :meth:`release` or process exit."""

    def __init__(self, run_dir: str | Path) -> None:
        import fcntl

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
        """Drop the lock (closing the descriptor releases the flock); the file stays, it holds no state."""
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None

    def __del__(self) -> None:
        self.release()


def lock_holder(run_dir: str | Path) -> str | None:
    """``"process 7438"`` when a live process holds ``run_dir``'s lock, else None (nothing is created:
    a directory without a lock file has no writer). For tools that must not touch a run in use."""
    import fcntl

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
    """The file handler of ``mcrs-train``'s log (``hydra.job_logging`` in ``conf/config.yaml``): it claims
    the run directory before it opens the log.

    For each job Hydra makes the folder, then sets up the job's log, then writes ``.hydra/`` there, in the
    process that runs the job (whatever the launcher). A single run is already claimed; a sweep's job is
    claimed here. A job whose folder a live process holds, or that holds another run (without
    ``overwrite=true``), stops the sweep in one line, and nothing is written into the folder. A sweep that
    went on would leave a hole its summary hides."""

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
    """Why a fresh run may not start in ``run_dir`` (:func:`prepare_fresh`), or None (also when it does
    not exist). :class:`mcrs.experiment.commands.cli.RunDirCheck` asks before Hydra writes its ``.hydra/`` files
    there, so that a refused command leaves an existing run as it was."""
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
    """Refuse a run directory that holds anything but Hydra's files, or clear a previous run from it.

    With ``overwrite`` only a previous run's own files are removed (:data:`RUN_ARTEFACTS`); a directory
    holding anything else is refused either way, so ``overwrite=true`` never deletes unrelated files.
    """
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
    """``train/episodes`` for ``<run>/logs/scalars/train/episodes.csv`` (the name it was logged under)."""
    return path.relative_to(run_dir / "logs" / "scalars").with_suffix("").as_posix()


def truncate_csv_logs(run_dir: Path, rows: Mapping[str, int] | None, env_steps: int) -> dict[str, int]:
    """Keep the rows each CSV log had when the checkpoint was written; drop those written after it.

    ``rows`` (name -> row count) comes from the checkpoint; a checkpoint without it (older runs) keeps the
    rows logged at or before its ``env_steps``. Each file is rewritten atomically. Returns the rows kept.
    """
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
    """What a checkpoint must share with the run that resumes from it, flat and ordered.

    ``format.version``, then every config field a resume may not change (algo, env shape and dynamics,
    model, seed, the training settings; not the ``mutable`` ones), then ``networks.<module>.<tensor>``:
    the shape of every learned tensor. Plain strings, numbers and lists: it is stored in the checkpoint.
    """
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
    """``"algo.name: 'cnn_semu' in the checkpoint, 'qmix' in this run"`` for the first field that
    differs (in ``current``'s order, then fields only the checkpoint has), or None when they match.

    A config field on one side only is a field added to (or dropped from) the schema since the checkpoint
    was written, not another run: it is skipped. A network tensor on one side only is a difference.
    """
    for key in [*current, *(k for k in saved if k not in current)]:
        if (key not in saved or key not in current) and not key.startswith("networks."):
            continue
        theirs, ours = saved.get(key, "<missing>"), current.get(key, "<missing>")
        if theirs != ours:
            return f"{key}: {theirs!r} in the checkpoint, {ours!r} in this run"
    return None


# ---------------------------------------------------------------------------------------- I/O errors
def describe_os_error(error: OSError) -> str:
    """``"No space left on device (writing /run/checkpoints/x.pt)"``: the reason and the file, one line."""
    reason = error.strerror or str(error) or type(error).__name__
    return f"{reason} ({error.filename})" if error.filename else reason


@contextlib.contextmanager
def io_errors(action: str, after: str | Callable[[], str] = ""):
    """Turn an ``OSError`` inside the block into a one-line :class:`RunDirError` (``action``: what was
    being done, ``after``: what is still intact, or a function that says it once the error happened: a
    save may have written ``last.pt`` before failing on the next file)."""
    try:
        yield
    except OSError as error:
        intact = after() if callable(after) else after
        raise RunDirError(f"cannot {action}: {describe_os_error(error)}{intact}") from None
