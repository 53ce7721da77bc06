"""Records: the small, committed evidence of a run (``results/records/...json``).

Run directories are not committed (a map20 checkpoint is gigabytes), so each finished or stopped run
leaves a record: its resolved config, the evaluation learning curves (every ``eval/`` metric and the
mean Q_tot, as logged), the final evaluation, how far it got, how long it took, the git commit and the
machine. ``mcrs-report`` reads records as it reads run directories (mcrs_lab.analysis.runs), so the
committed records alone regenerate the report. ``mcrs-eval`` results (the heuristics) get records too.

    results/records/<experiment>/<budget>/<map>_<algo>[_<swept value>]_seed<k>.json    (mcrs-train)
    results/records/<study>/<map>/<policy>_rc<R_c>_seed<k>.json                        (mcrs-eval)
"""

from __future__ import annotations

import datetime
import functools
import json
import os
import platform
import subprocess
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.schema import CONFIG_DIR
from mcrs.experiment.util.atomic import ChangedSinceRead, write_if_unchanged
from mcrs.experiment.util.untrusted import (
    MAX_DEPTH,
    UntrustedInput,
    confined,
    depth_of,
    plain_name,
    read_yaml,
)
from mcrs_lab.analysis.curves import Q_TOT
from mcrs_lab.analysis.policy_identity import policy_label, trained_run_id
from mcrs_lab.analysis.record_schema import RecordError
from mcrs_lab.analysis.runs import (
    RECORD_FORMAT,
    RECORD_VERSION,
    EvaluationRow,
    TrainingRun,
    find_runs,
    is_heuristic_policy,
    read_record,
    read_scalar_rows,
)

#: Where records go by default (committed), relative to the repository root.
RECORDS_DIR = Path("results/records")
#: The file in a run directory where ``mcrs-campaign run`` notes each session (one JSON line each).
SESSIONS = "campaign.jsonl"
#: Swept fields and their short names in record names (the presets' ``hydra.sweep.subdir``).
NAME_FIELDS = {
    "env.comm_range": "rc",
    "algo.memory.delta": "delta",
    "algo.memory_weight": "lambda",
    "algo.incentive_threshold": "thr",
    "algo.gamma": "gamma",
}


# ----------------------------------------------------------------------------------------- names
@functools.cache
def swept_fields(experiment: str) -> tuple[str, ...]:
    """The fields that ``conf/experiment/<experiment>.yaml`` sweeps besides map, algorithm and seed."""
    path = Path(CONFIG_DIR, "experiment", f"{experiment}.yaml")
    if not path.is_file():
        return ()
    params = OmegaConf.select(OmegaConf.load(path), "hydra.sweeper.params") or {}
    return tuple(k for k in params if k not in ("env", "algo", "seed") and k in NAME_FIELDS)


def point_name(env: str, algo: str, seed: int, settings: dict[str, Any]) -> str:
    """``map20_emc_delta0.13_seed0``: the map, the algorithm, each swept value (short name) and the seed."""
    swept = [f"{NAME_FIELDS[k]}{float(v):g}" for k, v in settings.items()]
    return "_".join([env, algo, *swept, f"seed{seed}"])


def _component(value: Any, what: str, source: str = "the run's config.yaml") -> str:
    """A value from a run's files (``source``) that becomes one path component under the records: a
    plain name, or a one-line RecordError naming the field and the file."""
    try:
        return plain_name(value, what)
    except UntrustedInput as error:
        raise RecordError(f"{error} (in {source})") from None


def under_root(path: Path, root: Path) -> Path:
    """``path`` if it lies under ``root`` once resolved (a record is never written elsewhere)."""
    try:
        confined(path, root, "the record's path")
    except UntrustedInput as error:
        raise RecordError(str(error)) from None
    return path


def training_record_path(root: Path, config: dict[str, Any]) -> Path:
    experiment = _component(config.get("experiment", "none"), "experiment")
    budget = _component(config.get("budget", "none"), "budget")
    run = TrainingRun(Path(), config)
    _component(run.env_name, "env.name")
    _component(run.algo_name, "algo.name")
    if (
        isinstance(run.config.get("seed"), bool)
        or not isinstance(run.config.get("seed"), int)
        or run.seed < 0
    ):
        raise RecordError(f"seed={run.config.get('seed')!r} (the run's config.yaml): not a whole number >= 0")
    settings = {k: run.setting(k) for k in swept_fields(experiment)}
    name = point_name(run.env_name, run.algo_name, run.seed, settings)
    file = _component(f"{name}.json", "the point's name")
    return under_root(root / experiment / budget / file, root)


# ---------------------------------------------------------------------------------------- facts
def cpuinfo(key: str) -> str | None:
    """The first value of ``key`` in /proc/cpuinfo (``model name``, ``vendor_id``); None off Linux."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.split(":", 1)[0].strip() == key:
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return None


def machine_facts() -> dict[str, Any]:
    """What the machine was: CPUs, torch, the load (a shared machine runs slower). A run's torch threads
    are its config's ``threads`` (kept in its record). The CPU capability is the kernel set torch
    dispatches to (AVX2, AVX512): two machines of another model or capability round differently, so the
    same seed trains to other figures there."""
    import torch

    return {
        "cpu_count": os.cpu_count(),
        "cpu_model": cpuinfo("model name") or platform.processor() or platform.machine(),
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "torch": torch.__version__,
        "load_avg": [round(x, 2) for x in os.getloadavg()],
        "python": platform.python_version(),
    }


def git_facts() -> dict[str, Any]:
    """The commit of the mcrs source in use, and whether it had uncommitted changes."""
    root = Path(__file__).resolve().parent.parent.parent
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=10, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no", "--", "mcrs", "conf"],
            cwd=root,
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "dirty": None}
    return {"commit": commit, "dirty": bool(dirty)}


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def _shown(path: Path) -> str:
    """``path`` relative to the working directory when inside it (records are committed), else absolute."""
    path = path.resolve()
    try:
        return str(path.relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def loop_time_s(run_dir: Path) -> float | None:
    """Seconds of the training loop, summed over sessions (a resumed run restarts its clock).

    Each ``time/`` row holds the session's cumulative seconds and its env steps per second since the
    session began, so ``step - rate * seconds`` names the session a row belongs to.
    """
    folder = run_dir / "logs" / "scalars" / "time"
    parts = [read_scalar_rows(p) for p in sorted(folder.glob("*_s.csv")) if p.stem != "env_steps_per_s"]
    rate_file = folder / "env_steps_per_s.csv"
    if not parts or not rate_file.is_file():
        return None
    rates = read_scalar_rows(rate_file)
    if any(len(p) != len(rates) for p in parts):
        return None
    sessions: dict[int, float] = {}
    for k, (step, rate) in enumerate(rates):
        elapsed = sum(p[k][1] for p in parts)
        start = round((step - rate * elapsed) / 100)  # to the nearest 100 steps: float rounding
        sessions[start] = max(sessions.get(start, 0.0), elapsed)
    return round(sum(sessions.values()), 1)


def _sessions(run_dir: Path) -> list[dict[str, Any]]:
    path = run_dir / SESSIONS
    if not path.is_file():
        return []
    sessions = []
    for number, line in enumerate(path.read_text(errors="replace").splitlines(), start=1):
        if not line.strip():
            continue
        try:
            session = json.loads(line, parse_constant=lambda name: None)
        except (ValueError, RecursionError):
            raise RecordError(
                f"{path}:{number}: not a JSON line (campaign sessions are one object a line)"
            ) from None
        if not isinstance(session, dict) or depth_of(session) > MAX_DEPTH:
            raise RecordError(f"{path}:{number}: not a session (a flat JSON object)")
        sessions.append(session)
    return sessions


# -------------------------------------------------------------------------------------- records
def _finished(checkpoint_steps: int | None, total: int, final_step: int | None) -> bool:
    """At its length with its final evaluation logged: a run killed between its last checkpoint and its
    final evaluation is stopped (a resume evaluates it), not finished."""
    if checkpoint_steps is None or checkpoint_steps < total:
        return False
    return final_step is not None and final_step >= checkpoint_steps


def training_record(run_dir: Path) -> dict[str, Any]:
    """The record of an ``mcrs-train`` run directory (finished, stopped or still running)."""
    runs = find_runs([run_dir])
    found = [r for r in runs.training if r.path.resolve() == run_dir.resolve()]
    if not found:
        reasons = "; ".join(s.reason for s in runs.skipped) or "no config.yaml with logs/ or checkpoints/"
        raise RecordError(f"{run_dir}: not an mcrs-train run directory with CSV logs ({reasons})")
    run = found[0]
    names = sorted(p.relative_to(run_dir / "logs" / "scalars").with_suffix("").as_posix()
                   for p in (run_dir / "logs" / "scalars" / "eval").glob("*.csv"))  # fmt: skip
    scalars = {}
    for name in [*names, Q_TOT]:
        found_scalar = run.scalar(name)
        if found_scalar is not None:
            scalars[name] = [[int(s), float(v)] for s, v in zip(*found_scalar, strict=True)]
    total = int(run.setting("train.total_env_steps"))
    checkpoint_steps = None
    last = ckpt.checkpoint_path(run_dir)
    if last.is_file():
        state = ckpt.load(last, mmap=True)
        checkpoint_steps = int(state["counters"]["env_steps"])
        total = int(state["config"]["train"]["total_env_steps"])  # a resume may have extended the run
    reward = scalars.get("eval/episode_reward", [])
    final_step = reward[-1][0] if reward else None
    final = {n.split("/", 1)[1]: dict(scalars[n]).get(final_step) for n in names if final_step is not None}
    logged = max((rows[-1][0] for rows in scalars.values() if rows), default=0)
    return {
        "format": RECORD_FORMAT,
        "version": RECORD_VERSION,
        "kind": "training",
        "run_dir": _shown(run_dir),
        "status": "finished" if _finished(checkpoint_steps, total, final_step) else "stopped",
        "total_env_steps": total,
        "checkpoint_env_steps": checkpoint_steps,  # where a resume would start
        "logged_env_steps": logged,  # the last step with a metric (past the checkpoint if stopped)
        "loop_time_s": loop_time_s(run_dir),
        "torch_threads": _threads(run.config.get("threads")),
        "final_eval": {"env_step": final_step, **final},
        "sessions": _sessions(run_dir),
        "config": run.config,
        "recorded": {"at": _now(), "git": git_facts(), "machine": machine_facts()},
        "scalars": scalars,
    }


def evaluation_record(eval_dir: Path) -> dict[str, Any]:
    """The record of an ``mcrs-eval`` result directory (``metrics.csv``, one row per policy)."""
    runs = find_runs([eval_dir])
    rows: list[EvaluationRow] = [e for e in runs.evaluations if e.path.resolve() == eval_dir.resolve()]
    if not rows:
        reasons = "; ".join(s.reason for s in runs.skipped) or "no metrics.csv"
        raise RecordError(f"{eval_dir}: not an mcrs-eval result ({reasons})")
    hydra_dir = eval_dir / ".hydra"
    try:  # bounded before parsing (mcrs.experiment.util.untrusted); Hydra's files keep their interpolations
        config = read_yaml(hydra_dir / "config.yaml") if hydra_dir.is_dir() else {}
        hydra = read_yaml(hydra_dir / "hydra.yaml") if (hydra_dir / "hydra.yaml").is_file() else {}
    except UntrustedInput as error:
        raise RecordError(str(error)) from None
    if not isinstance(config, dict) or not isinstance(hydra, dict):
        raise RecordError(f"{hydra_dir}: config.yaml and hydra.yaml must be mappings")
    choices = ((hydra.get("hydra") or {}).get("runtime") or {}).get("choices")
    study = (choices if isinstance(choices, dict) else {}).get("study") or "eval"
    return {
        "format": RECORD_FORMAT,
        "version": RECORD_VERSION,
        "kind": "evaluation",
        "run_dir": _shown(eval_dir),
        "study": study,
        "policy": str(config.get("policy", rows[0].policy)),
        "config": config,
        "rows": [
            {
                "policy": r.policy,
                "env": r.env_name,
                "comm_range": r.comm_range,
                "seed": r.seed,
                "episodes": r.episodes,
                "means": r.means,
                "label": None if r.is_heuristic else policy_label(r.policy),
                "run": trained_run_id(r.policy),
            }
            for r in rows
        ],
        "recorded": {"at": _now(), "git": git_facts(), "machine": machine_facts()},
    }


def evaluation_record_name(policy: str, comm_range: str, seed: int | str) -> str:
    """``greedy_rc5_seed0.json``, ``trained-qmix-<experiment>-<run folder>_rc5_seed0.json``: the one naming
    rule (``comm_range`` may be a glob's ``*``)."""
    return f"{policy}_rc{comm_range}_seed{seed}.json"


def trained_policy_name(label: str | None, run: str) -> str:
    """The policy part of a trained policy's record name: its label and its run, ``/`` as ``-``
    (``trained qmix``, ``shields_view/map20_qmix_seed0`` -> ``trained-qmix-shields_view-map20_qmix_seed0``)."""
    return f"{(label or 'trained').replace(' ', '-')}-{run.replace('/', '-')}"


def evaluation_record_path(root: Path, record: dict[str, Any]) -> Path:
    row = record["rows"][0]
    policy = record["policy"]
    if not is_heuristic_policy(policy):  # a trained agent: its algorithm and its run (experiment and folder)
        run = Path(policy)
        run = run.parent.parent if run.suffix == ".pt" else run
        # Records made before ``run`` was kept name the folder alone (two experiments' runs of one name
        # collided: mcrs_lab.campaign.evaluations reads those by their policy path).
        policy = trained_policy_name(row["label"], row.get("run") or run.name)
    name = evaluation_record_name(policy, f"{row['comm_range']:g}", row["seed"])
    study = _component(record["study"], "study", "the result's .hydra/hydra.yaml")
    env = _component(row["env"], "env", "the result's metrics.csv")
    return under_root(root / study / env / _component(name, "the record's file name", "the result"), root)


def _threads(setting: object) -> object:
    """The run's ``threads`` as a record says it (``auto``: chosen from the load when the run started)."""
    if setting in (None, 0, "0"):
        return "torch's default (one per core)"
    if setting == "auto":
        return "auto (the cores the load average left free at the start)"
    return int(setting) if str(setting).isdigit() else setting


def make_record(run_dir: Path, root: Path = RECORDS_DIR) -> tuple[Path, dict[str, Any]]:
    """The record of a training run or an evaluation result, and where it belongs under ``root``."""
    if (run_dir / "config.yaml").is_file():
        record = training_record(run_dir)
        return training_record_path(root, record["config"]), record
    if (run_dir / "metrics.csv").is_file():
        record = evaluation_record(run_dir)
        return evaluation_record_path(root, record), record
    raise RecordError(
        f"{run_dir}: neither an mcrs-train run (config.yaml) nor an mcrs-eval result (metrics.csv)"
    )


def _evidence(record: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in record.items() if k != "recorded"}


def dumps(record: dict[str, Any]) -> str:
    """JSON with one line per metric series: readable, and small diffs when a record is updated."""
    lines = []
    for key, value in record.items():
        if key == "scalars":
            inner = ",\n".join(
                f"    {json.dumps(n)}: {json.dumps(v, separators=(',', ':'))}" for n, v in value.items()
            )
            lines.append(f'  "scalars": {{\n{inner}\n  }}')
        else:
            text = json.dumps(value, indent=2).replace("\n", "\n  ")
            lines.append(f"  {json.dumps(key)}: {text}")
    return "{\n" + ",\n".join(lines) + "\n}\n"


def write_record(path: Path, record: dict[str, Any], replace: bool = False) -> str:
    """Write ``record`` atomically; ``"unchanged"`` when the same evidence is already there (recording
    twice changes nothing), ``"updated"`` or ``"written"`` otherwise. A record of another run
    directory at ``path`` is kept unless ``replace`` (two runs of one point need a choice), or unless it
    was stopped and this run finished. The file is replaced only if it is still what was read (another
    process recording the same point meanwhile keeps its record, and this one is refused in one line)."""
    outcome = "written"
    before = path.read_bytes() if path.is_file() else None
    if before is not None:
        old = read_record(path)
        if old is not None and _evidence(old) == json.loads(json.dumps(_evidence(record))):
            return "unchanged"
        overtakes = old is not None and old.get("status") == "stopped" and record.get("status") == "finished"
        if old is not None and old.get("run_dir") != record["run_dir"] and not (replace or overtakes):
            raise RecordError(
                f"{path} records another run ({old.get('run_dir')}); pass --replace to record "
                f"{record['run_dir']} there instead"
            )
        outcome = "updated"
    try:
        write_if_unchanged(path, dumps(record).encode(), before)
    except ChangedSinceRead as error:
        raise RecordError(str(error)) from None
    return outcome
