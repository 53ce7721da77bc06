"""Finding and reading the run directories that ``mcrs-report`` turns into figures and tables.

Three kinds of file count as runs:

- an ``mcrs-train`` run: ``config.yaml`` (the resolved config) beside its metrics and ``checkpoints/``.
  The metrics are read from ``logs/scalars/<group>/<name>.csv`` (TorchRL's CSV logger, one ``step,value``
  row per point; ``logger=csv``, and ``logger=wandb``, which keeps the same files beside its wandb run)
  or from TensorBoard's event files in ``logs/`` (``logger=tensorboard``, read with TensorBoard's own
  ``EventAccumulator``);
- an ``mcrs-eval`` result: ``metrics.csv`` with one row per policy (map, R_c, seed, mean and std of
  every episode metric);
- a record (``mcrs-campaign record``, mcrs_lab.analysis.records): a small JSON file holding either of the
  above, so that committed records give the same report as the run directories they came from.

Anything else under the given paths is ignored; a directory that looks like a run but cannot be read is
reported as skipped, with the reason.
"""

from __future__ import annotations

import csv
import functools
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import OmegaConf

from mcrs.experiment.run.history import current_config, legacy_values
from mcrs.experiment.run.logging import ScalarFileError, flatten_config, scalar_file
from mcrs.experiment.run.logging import read_scalar_rows as logged_rows
from mcrs.experiment.run.logging import sorted_points as _sorted_points
from mcrs.experiment.schema import CONFIG_DIR
from mcrs.experiment.util.untrusted import UntrustedInput, read_yaml
from mcrs_lab.analysis.evaluation_rows import (  # noqa: F401 (EvaluationRow: read from here by the tools)
    EvaluationRow,
    env_node,
    evaluation_config,
    is_heuristic_policy,
)
from mcrs_lab.analysis.record_schema import (  # noqa: F401 (RECORD_FORMAT: read from here by the tools)
    RECORD_FORMAT,
    RECORD_VERSION,
    RecordError,
    SchemaField,
    check_row,
    deduplicate,
    load_json_record,
)

#: Config fields that never tell two runs' methods apart: seeds, resources, reporting, run bookkeeping.
NOT_A_SETTING = (
    "seed",
    "resume",
    "threads",
    "report",
    "device",
    "logger",
    "experiment",
    "budget",
    "train.total_env_steps",
    "train.eval_interval",
    "train.checkpoint_interval",
    "train.collector",
    "train.collector_workers",
    "train.save_replay",
    "train.checkpoint_minutes",
    "train.keep_checkpoints",
    "overwrite",
)
#: Short names of the swept fields in labels (the paper's symbols).
SHORT_NAMES = {
    "algo.memory_weight": "lambda",
    "algo.memory.delta": "delta",
    "env.comm_range": "R_c",
    "algo.incentive_threshold": "R_thr",
}


@dataclass(frozen=True)
class Skipped:
    """A run left out of (part of) the report, and why."""

    path: Path
    reason: str


@dataclass
class TrainingRun:
    """One ``mcrs-train`` run: its directory, or a record of it (``scalars`` then holds every metric)."""

    path: Path
    config: dict[str, Any]
    scalars: dict[str, tuple[np.ndarray, np.ndarray]] | None = None
    _cache: dict[str, tuple[np.ndarray, np.ndarray] | None] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        # A record or run made before a field existed is read as it was made (env.safety_rule=near, ...).
        self.legacy = legacy_values(self.config)
        self.config = current_config(self.config)

    @property
    def env_name(self) -> str:
        return str(self.config["env"]["name"])

    @property
    def algo_name(self) -> str:
        return str(self.config["algo"]["name"])

    @property
    def seed(self) -> int:
        return int(self.config["seed"])

    def setting(self, dotted: str) -> Any:
        """The value of a dotted config field (``algo.memory.delta``), or None when absent."""
        node: Any = self.config
        for part in dotted.split("."):
            if not isinstance(node, dict) or part not in node:
                return None
            node = node[part]
        return node

    def scalar(self, name: str) -> tuple[np.ndarray, np.ndarray] | None:
        """``(steps, values)`` of the logged metric ``name`` (``eval/episode_reward``), sorted by step;
        None when the run did not log it. A resumed run's repeated steps keep the last value."""
        if self.scalars is not None:  # a record: what it holds is all there is
            return self.scalars.get(name)
        if name not in self._cache:
            path = scalar_file(self.path, name)
            self._cache[name] = _read_scalar_csv(path) if path.is_file() else None
        return self._cache[name]


@dataclass
class Runs:
    """Everything found under the report's paths."""

    training: list[TrainingRun] = field(default_factory=list)
    evaluations: list[EvaluationRow] = field(default_factory=list)
    skipped: list[Skipped] = field(default_factory=list)


def read_scalar_rows(path: Path) -> list[tuple[int, float]]:
    """The ``step,value`` rows of a CSV-logger file in the order written (:func:`mcrs.experiment.run.logging.
    read_scalar_rows`); a bad row is refused as a :class:`RecordError`."""
    try:
        return logged_rows(path)
    except ScalarFileError as error:
        raise RecordError(str(error)) from None


def _read_scalar_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    return _sorted_points(read_scalar_rows(path))


def _is_hidden(path: Path, root: Path) -> bool:
    return any(part.startswith(".") for part in path.relative_to(root).parts)


def find_runs(paths: list[Path]) -> Runs:
    """All training runs, evaluation results and records under ``paths`` (each a run, a record or a
    folder of them). A record of a run directory that is also given counts once (the directory)."""
    runs = Runs()
    seen: set[Path] = set()
    records: list[tuple[Path, dict[str, Any]]] = []
    for root in paths:
        root = Path(root)
        if not root.exists():
            runs.skipped.append(Skipped(root, "no such file or directory"))
            continue
        candidates = [root / "config.yaml", root / "metrics.csv"] if root.is_dir() else [root]
        if root.is_dir():
            candidates += sorted(root.rglob("config.yaml")) + sorted(root.rglob("metrics.csv"))
            candidates += sorted(root.rglob("*.json"))
        for file in candidates:
            if not file.is_file() or file in seen or (root.is_dir() and _is_hidden(file, root)):
                continue
            seen.add(file)
            if file.name == "config.yaml":
                _add_training_run(file.parent, runs)
            elif file.name == "metrics.csv":
                _add_evaluation(file, runs)
            elif file.suffix == ".json" and (record := read_record(file, runs.skipped)) is not None:
                records.append((file, record))
    directories = {r.path.resolve() for r in runs.training} | {e.path.resolve() for e in runs.evaluations}
    records, copies = deduplicate(records)  # a copied record counts once; a contradictory one is refused
    runs.skipped += [Skipped(file, reason) for file, reason in copies]
    for file, record in records:
        if Path(record.get("run_dir", "")).resolve() in directories:
            runs.skipped.append(Skipped(file, f"a record of {record['run_dir']}, which is read itself"))
        else:
            _add_record(file, record, runs)
    return runs


def read_record(path: Path, skipped: list[Skipped] | None = None) -> dict[str, Any] | None:
    """The record in ``path``, checked against the schema (mcrs_lab.analysis.record_schema); None for a JSON
    file that is not a record, or a record of another version (added to ``skipped`` with the reason). A
    record that fails the schema raises ``RecordError`` naming the file and the field."""
    record = load_json_record(path)
    if record is None:
        return None
    if record.get("version") != RECORD_VERSION:
        if skipped is not None:
            skipped.append(
                Skipped(path, f"record version {record.get('version')}; this mcrs reads {RECORD_VERSION}")
            )
        return None
    return record


def _add_record(path: Path, record: dict[str, Any], runs: Runs) -> None:
    if record.get("kind") == "training":
        scalars = {name: _sorted_points(rows) for name, rows in record["scalars"].items()}
        runs.training.append(TrainingRun(path, record["config"], scalars=scalars))
    elif record.get("kind") == "evaluation":
        for row in record["rows"]:
            runs.evaluations.append(
                EvaluationRow(
                    path,
                    row["policy"],
                    row["env"],
                    float(row["comm_range"]),
                    int(row["seed"]),
                    int(row["episodes"]),
                    {k: float(v) for k, v in row["means"].items()},
                    row.get("label"),
                    row.get("run"),
                    env_node(record.get("config")),
                )
            )
    else:
        runs.skipped.append(Skipped(path, f"record of unknown kind {record.get('kind')!r}"))


def _add_training_run(run_dir: Path, runs: Runs) -> None:
    if not (run_dir / "checkpoints").is_dir() and not (run_dir / "logs").is_dir():
        return  # a config.yaml that is not an mcrs-train run (e.g. a user's own file)
    try:  # bounded before parsing: an alias bomb or a deep file is refused unexpanded
        config = read_yaml(run_dir / "config.yaml", interpolations=False)
    except UntrustedInput as error:  # unreadable YAML: say so, keep going
        runs.skipped.append(Skipped(run_dir, f"config.yaml cannot be read ({error})"))
        return
    if not isinstance(config, dict) or not all(k in config for k in ("env", "algo", "seed")):
        runs.skipped.append(Skipped(run_dir, "config.yaml is not an mcrs-train config (no env/algo/seed)"))
        return
    if (run_dir / "logs" / "scalars").is_dir():
        runs.training.append(TrainingRun(run_dir, config))
        return
    if any((run_dir / "logs").glob("events.out.tfevents.*")):
        try:
            scalars = read_tensorboard_scalars(run_dir / "logs")
        except Exception as error:  # a truncated or foreign event file: say so, keep going
            runs.skipped.append(Skipped(run_dir, f"TensorBoard events cannot be read ({error})"))
            return
        if not scalars:
            runs.skipped.append(Skipped(run_dir, "its TensorBoard event files hold no scalars"))
            return
        runs.training.append(TrainingRun(run_dir, config, scalars=scalars))
        return
    backend = (config.get("logger") or {}).get("backend", "?")
    hint = (
        " (a wandb run written before mcrs kept its CSV history beside it: sync it and export the history)"
        if (run_dir / "wandb").is_dir()
        else ""
    )
    runs.skipped.append(Skipped(run_dir, f"no metrics found (logger.backend={backend}){hint}"))


def read_tensorboard_scalars(log_dir: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Every scalar of the TensorBoard event files directly in ``log_dir`` (those of a resumed run too, in
    the order written): ``{name: (steps, values)}``, a repeated step keeping its last value."""
    from tensorboard.backend.event_processing.event_accumulator import SCALARS, EventAccumulator

    events = EventAccumulator(str(log_dir), size_guidance={SCALARS: 0})  # 0: keep every point
    events.Reload()
    return {
        name: _sorted_points([(e.step, e.value) for e in events.Scalars(name)])
        for name in events.Tags()["scalars"]
    }


def _add_evaluation(path: Path, runs: Runs) -> None:
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    needed = {"policy", "env", "comm_range", "seed", "episodes"}
    if not rows or not needed <= set(rows[0]):
        missing = sorted(needed - set(rows[0])) if rows else ["every row"]
        runs.skipped.append(Skipped(path.parent, f"metrics.csv lacks {', '.join(missing)} (rerun mcrs-eval)"))
        return
    for line, row in enumerate(rows, start=2):
        try:  # every value is checked as a record's row is (mcrs_lab.analysis.record_schema)
            record_row = {
                "policy": row["policy"],
                "env": row["env"],
                "comm_range": float(row["comm_range"]),
                "seed": int(row["seed"]),
                "episodes": int(row["episodes"]),
                "means": {k[: -len("_mean")]: float(v) for k, v in row.items() if k.endswith("_mean")},
            }
            check_row(record_row, f"line {line}: ")
        except (ValueError, TypeError, SchemaField) as error:
            raise RecordError(f"{path}: line {line}: {error}") from None
        env_name = record_row.pop("env")
        env = env_node(evaluation_config(path.parent))
        runs.evaluations.append(EvaluationRow(path.parent, env_name=env_name, env=env, **record_row))


def flatten(config: dict[str, Any]) -> dict[str, Any]:
    """Dotted names to values; lists become tuples so that values compare and hash."""
    return {k: tuple(v) if isinstance(v, list) else v for k, v in flatten_config(config).items()}


def _is_setting(name: str) -> bool:
    return not any(name == n or name.startswith(n + ".") for n in NOT_A_SETTING)


@functools.cache
def group_fields(group: str) -> frozenset[str]:
    """The fields that a config group's options set (``conf/<group>/*.yaml``): for ``budget`` run length,
    batch and buffer sizes; for ``preset`` the learner's optimiser, targets and batches."""
    out: set[str] = set()
    for path in sorted(Path(CONFIG_DIR, group).glob("*.yaml")):
        out |= {
            k for k in flatten(OmegaConf.to_container(OmegaConf.load(path))) if not k.startswith("hydra.")
        }
    return frozenset(out)


def budget_fields() -> frozenset[str]:
    """The fields that the budget presets set (conf/budget/*.yaml): run length, batch sizes, buffer sizes."""
    return group_fields("budget")


def _explained_by_preset(configs: list[dict[str, Any]], name: str) -> bool:
    """Whether field ``name`` differs between ``configs`` only as their ``preset`` does: a field the
    presets set, one value within each preset (so ``preset=pymarl2`` labels those runs, not its seven
    fields; a field swept within one preset still shows)."""
    if name == "preset":
        return True
    if name not in group_fields("preset"):
        return False
    by_preset: dict[str, set[str]] = {}
    for config in configs:
        by_preset.setdefault(repr(config.get("preset")), set()).add(repr(config.get(name)))
    return all(len(values) == 1 for values in by_preset.values())


@functools.cache
def default_fields(algo: str, env: str) -> dict[str, Any] | None:
    """The flattened config ``mcrs-train algo=<algo> env=<env>`` runs with today; None for an algorithm
    or map the packaged presets do not have."""
    from mcrs.experiment.config import ConfigError, as_dictconfig, compose

    try:
        config = compose(f"algo={algo}", f"env={env}")
    except ConfigError:
        return None
    return flatten(OmegaConf.to_container(as_dictconfig(config), resolve=True))  # as config.yaml holds it


def comparable_config(run: TrainingRun) -> dict[str, Any]:
    """The run's settings as today's config names them: a field the run's code did not have yet takes
    today's default (a feature added later, off by default), and a field today's config no longer has
    is left out. So runs recorded by different versions of the code compare on what they share."""
    config = flatten(run.config)
    defaults = default_fields(run.algo_name, run.env_name)
    if defaults is None:
        return config
    return {name: config.get(name, default) for name, default in defaults.items()}


def label_fields(runs: list[TrainingRun]) -> dict[str, list[str]]:
    """Per algorithm name, the settings that differ between its runs (the swept ones, e.g. delta).

    Runs of different budgets differ in many fields at once (steps, batch and buffer sizes): they are told
    apart by ``budget`` alone; runs of different learner presets by ``preset`` and the fields that differ
    within a preset. The memory's fields do not count for an algorithm without a memory.
    """
    by_algo: dict[str, list[dict[str, Any]]] = {}
    for run in runs:
        by_algo.setdefault(run.algo_name, []).append(comparable_config(run))
    budget = budget_fields()
    out = {}
    for algo, configs in by_algo.items():
        names = sorted({k for c in configs for k in c})
        memory = any(c.get("algo.memory.enabled") for c in configs)
        varying = [
            n
            for n in names
            if _is_setting(n)
            and n not in budget
            and (memory or not n.startswith("algo.memory."))
            and len({repr(c.get(n)) for c in configs}) > 1
        ]
        if len({c.get("preset") for c in configs}) > 1:
            varying = ["preset", *(n for n in varying if not _explained_by_preset(configs, n))]
        if len({c.get("budget") for c in configs}) > 1:
            varying.insert(0, "budget")
        out[algo] = varying
    return out


def _short(name: str) -> str:
    return SHORT_NAMES.get(name, name.split(".")[-1])


def _format(value: Any) -> str:
    if value is None:
        return "none"
    return f"{value:g}" if isinstance(value, float) else str(value)


def run_labels(runs: list[TrainingRun]) -> dict[Path, str]:
    """A label per run: its algorithm, plus the settings swept within that algorithm
    (``cnn_semu lambda=0.5``). Runs with the same label are seeds of one method."""
    fields = label_fields(runs)
    labels = {}
    for run in runs:
        config = comparable_config(run)
        parts = [f"{_short(n)}={_format(config.get(n))}" for n in fields[run.algo_name]]
        labels[run.path] = " ".join([run.algo_name, *parts])
    return labels


def select_map(runs: Runs, env_name: str | None) -> str | None:
    """Keep the runs of one map (``env_name``, or the map with the most runs); the others are skipped
    with the reason. Returns the map's name (None when there is nothing to report)."""
    names = Counter([r.env_name for r in runs.training] + [e.env_name for e in runs.evaluations])
    if not names:
        return None
    chosen = env_name or names.most_common(1)[0][0]
    hint = " (pass --env to report it)" if env_name is None else ""
    kept = []
    for run in runs.training:
        if run.env_name == chosen:
            kept.append(run)
        else:
            runs.skipped.append(Skipped(run.path, f"map {run.env_name}, the report is on {chosen}{hint}"))
    runs.training = kept
    evaluations = []
    for row in runs.evaluations:
        if row.env_name == chosen:
            evaluations.append(row)
        else:
            runs.skipped.append(
                Skipped(row.path, f"evaluation on map {row.env_name}, the report is on {chosen}{hint}")
            )
    runs.evaluations = evaluations
    return chosen


def default_labels(runs: list[TrainingRun]) -> dict[str, str]:
    """Short names of labels, so that a claim names a method as the paper does and finds it whatever other
    sweeps of it sit in the same report: the algorithm alone for its runs at today's defaults (``emc`` ->
    ``emc delta=0.0013`` beside ``emc delta=0.13``); the algorithm with the one swept setting off its
    default, the others at theirs (``cnn_semu delta=0.13`` -> ``cnn_semu delta=0.13 lambda=0.1``); and, for
    runs at every default, the algorithm with any one of the paper's symbols at the run's value, swept or
    not (``cnn_semu lambda=0.1`` -> ``cnn_semu`` where no lambda sweep is in the report)."""
    fields, labels = label_fields(runs), run_labels(runs)
    out: dict[str, str] = {}
    for run in runs:
        names = fields[run.algo_name]
        defaults = default_fields(run.algo_name, run.env_name)
        if defaults is None:
            continue
        config = comparable_config(run)
        changed = [n for n in names if n not in defaults or repr(config.get(n)) != repr(defaults[n])]
        if len(changed) > 1:
            continue  # two settings off their defaults: only the full label names the run
        named = changed or [*names, *(n for n in SHORT_NAMES if n in config and n not in names)]
        if not changed:
            out.setdefault(run.algo_name, labels[run.path])
        for name in named:
            out.setdefault(f"{run.algo_name} {_short(name)}={_format(config.get(name))}", labels[run.path])
    return out
