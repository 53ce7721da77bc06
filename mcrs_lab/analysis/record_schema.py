"""The record's schema: every record is checked here when it is read, by every tool that reads one.

A record (mcrs_lab.analysis.records) is evidence: a wrong field would change a table silently. So a file
that carries the record marker is read with bounds (size, nesting, no NaN/Infinity literals) and each
field is checked for its type and range; a bad one is refused with the file and the field named::

    results/records/x.json: field rows[0].seed: -1 is not a whole number >= 0

:func:`deduplicate` then keeps one record per point: the same point recorded twice with the same
evidence (a copied file) counts once, and says so; twice with different evidence is refused, since it
would otherwise count as one more seed.
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path
from typing import Any

from mcrs.experiment.util.untrusted import MAX_DEPTH, UntrustedInput, depth_of, finite_number, plain_name

#: The marker and version of a record file (the first key of its JSON, so it is recognised cheaply).
RECORD_FORMAT = "mcrs-record"
RECORD_VERSION = 1
#: A record is a few tens of kB (a 2M-step run's curves): 16 MiB bounds the read and the parse.
MAX_RECORD_BYTES = 16 << 20
STATUSES = ("finished", "stopped")


class RecordError(ValueError):
    """A directory that cannot be recorded, a record that would overwrite another run's, or a record
    file that is refused (naming the file and the field)."""


class SchemaField(Exception):
    """A field that fails the schema: its dotted name and why (the caller adds the file)."""

    def __init__(self, field: str, why: str) -> None:
        super().__init__(f"field {field}: {why}")


def _refuse_constant(name: str) -> float:
    raise ValueError(f"{name} is not a number JSON allows")


def load_json_record(path: Path) -> dict[str, Any] | None:
    """The record in ``path``, checked; None for a JSON file without the record marker (not a record).

    A record-marked file that is too large, too deep, not JSON, holds NaN/Infinity, or fails the
    schema raises :class:`RecordError` naming the file (and the field)."""
    try:
        with open(path, "rb") as f:
            head = f.read(200)
            if RECORD_FORMAT.encode() not in head:
                return None
            data = head + f.read(MAX_RECORD_BYTES + 1 - len(head))
    except OSError as error:
        raise RecordError(f"{path}: cannot read the record ({error.strerror or error})") from None
    if len(data) > MAX_RECORD_BYTES:
        raise RecordError(f"{path}: a record larger than {MAX_RECORD_BYTES:,} bytes: refused unread")
    try:
        record = json.loads(data.decode("utf-8"), parse_constant=_refuse_constant)
    except RecursionError:
        raise RecordError(f"{path}: nested deeper than JSON can be read: refused") from None
    except (ValueError, UnicodeDecodeError) as error:
        raise RecordError(f"{path}: not a readable record ({str(error).splitlines()[0]})") from None
    if not isinstance(record, dict) or record.get("format") != RECORD_FORMAT:
        return None
    if depth_of(record) > MAX_DEPTH:
        raise RecordError(f"{path}: nested deeper than {MAX_DEPTH} levels: refused")
    if record.get("version") != RECORD_VERSION:
        return record  # another version: the caller skips it, saying which
    try:
        check_record(record)
    except SchemaField as error:
        raise RecordError(f"{path}: {error}") from None
    return record


# ------------------------------------------------------------------------------------------ checks
def _get(node: dict[str, Any], key: str, where: str) -> Any:
    if key not in node:
        raise SchemaField(f"{where}{key}", "missing")
    return node[key]


def _mapping(value: Any, field: str) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise SchemaField(field, f"{_shown(value)} is not a mapping")
    return value


def _text(value: Any, field: str) -> str:
    if not isinstance(value, str) or not value:
        raise SchemaField(field, f"{_shown(value)} is not a non-empty string")
    return value


def _name(value: Any, field: str) -> str:
    try:
        return plain_name(value, field)
    except UntrustedInput:
        raise SchemaField(field, f"{_shown(value)} is not a plain name (it names a folder)") from None


def _whole(value: Any, field: str, low: int = 0, none: bool = False) -> int | None:
    if none and value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise SchemaField(field, f"{_shown(value)} is not a whole number >= {low}")
    return value


def _number(value: Any, field: str, none: bool = False) -> float | None:
    if none and value is None:
        return None
    if not finite_number(value):
        raise SchemaField(field, f"{_shown(value)} is not a finite number")
    return float(value)


def _shown(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def check_record(record: dict[str, Any]) -> None:
    """Raise :class:`SchemaField` for the first field of ``record`` that the schema refuses."""
    kind = _get(record, "kind", "")
    _text(_get(record, "run_dir", ""), "run_dir")
    if kind == "training":
        _check_training(record)
    elif kind == "evaluation":
        _check_evaluation(record)
    else:
        raise SchemaField("kind", f"{_shown(kind)} is not one of training, evaluation")


def _check_training(record: dict[str, Any]) -> None:
    config = _mapping(_get(record, "config", ""), "config")
    _name(
        _get(_mapping(_get(config, "env", "config."), "config.env"), "name", "config.env."), "config.env.name"
    )
    algo = _mapping(_get(config, "algo", "config."), "config.algo")
    _name(_get(algo, "name", "config.algo."), "config.algo.name")
    _whole(_get(config, "seed", "config."), "config.seed")
    for label in ("experiment", "budget"):
        if label in config:
            _name(config[label], f"config.{label}")
    if _get(record, "status", "") not in STATUSES:
        raise SchemaField("status", f"{_shown(record['status'])} is not one of {', '.join(STATUSES)}")
    _whole(_get(record, "total_env_steps", ""), "total_env_steps")
    _whole(_get(record, "checkpoint_env_steps", ""), "checkpoint_env_steps", none=True)
    _whole(record.get("logged_env_steps", 0), "logged_env_steps")
    seconds = _number(record.get("loop_time_s"), "loop_time_s", none=True)
    if seconds is not None and seconds < 0:
        raise SchemaField("loop_time_s", f"{seconds} is negative")
    final = _mapping(_get(record, "final_eval", ""), "final_eval")
    for key, value in final.items():
        if key == "env_step":
            _whole(value, "final_eval.env_step", none=True)
        else:
            _number(value, f"final_eval.{key}", none=True)
    sessions = record.get("sessions", [])
    if not isinstance(sessions, list) or not all(isinstance(s, dict) for s in sessions):
        raise SchemaField("sessions", "not a list of mappings")
    scalars = _mapping(_get(record, "scalars", ""), "scalars")
    for name, rows in scalars.items():
        where = f"scalars.{name}"
        if not isinstance(rows, list):
            raise SchemaField(where, f"{_shown(rows)} is not a list of [step, value] rows")
        for k, row in enumerate(rows):
            if not isinstance(row, list) or len(row) != 2:
                raise SchemaField(f"{where}[{k}]", f"{_shown(row)} is not a [step, value] row")
            _whole(row[0], f"{where}[{k}] step")
            _number(row[1], f"{where}[{k}] value")


def _check_evaluation(record: dict[str, Any]) -> None:
    _name(_get(record, "study", ""), "study")
    _text(_get(record, "policy", ""), "policy")
    _mapping(record.get("config", {}), "config")
    rows = _get(record, "rows", "")
    if not isinstance(rows, list) or not rows:
        raise SchemaField("rows", f"{_shown(rows)} is not a non-empty list of rows")
    for k, row in enumerate(rows):
        _mapping(row, f"rows[{k}]")
        check_row(row, f"rows[{k}].")


def check_row(row: dict[str, Any], where: str) -> None:
    """One evaluation row (a record's, or a line of an mcrs-eval ``metrics.csv``)."""
    _text(_get(row, "policy", where), f"{where}policy")
    _name(_get(row, "env", where), f"{where}env")
    comm_range = _get(row, "comm_range", where)
    if not ((finite_number(comm_range) or comm_range == math.inf) and comm_range >= 0):
        raise SchemaField(f"{where}comm_range", f"{_shown(comm_range)} is not a distance >= 0")
    _whole(_get(row, "seed", where), f"{where}seed")
    _whole(_get(row, "episodes", where), f"{where}episodes", low=1)
    means = _mapping(_get(row, "means", where), f"{where}means")
    for metric, value in means.items():
        _number(value, f"{where}means.{metric}")
    for key in ("label", "run"):  # run: a trained policy's <experiment>/<run folder>
        value = row.get(key)
        if value is not None and not isinstance(value, str):
            raise SchemaField(f"{where}{key}", f"{_shown(value)} is not a string or null")


# ------------------------------------------------------------------------------------- duplicates
def _digest(value: Any) -> str:
    return hashlib.sha256(json.dumps(value, sort_keys=True).encode()).hexdigest()


def point_key(record: dict[str, Any]) -> str:
    """What identifies the point a record measures: its kind and full config (seed included), and for
    an evaluation the rows' policy, map, R_c, seed and episodes. Two records with one key are one point."""
    key: dict[str, Any] = {"kind": record["kind"], "config": record.get("config", {})}
    if record["kind"] == "evaluation":
        key["rows"] = [
            [r["policy"], r["env"], r["comm_range"], r["seed"], r["episodes"]] for r in record["rows"]
        ]
    return _digest(key)


def evidence_hash(record: dict[str, Any]) -> str:
    """The record's content without when, where and for which study it was recorded: equal for a copy."""
    return _digest({k: v for k, v in record.items() if k not in ("recorded", "run_dir", "study")})


def deduplicate(
    records: list[tuple[Path, dict[str, Any]]],
) -> tuple[list[tuple[Path, dict[str, Any]]], list[tuple[Path, str]]]:
    """One record per point: ``(kept, dropped)``, each dropped one with the reason (a copy of a kept one,
    by content hash). Two records of one point with different evidence raise :class:`RecordError`: one
    of them is wrong, and counting both would make one more seed."""
    first: dict[str, tuple[Path, str]] = {}
    kept, dropped = [], []
    for path, record in records:
        key, content = point_key(record), evidence_hash(record)
        if key not in first:
            first[key] = (path, content)
            kept.append((path, record))
        elif first[key][1] == content:
            dropped.append((path, f"a copy of {first[key][0]} (same content hash): counted once"))
        else:
            raise RecordError(
                f"{path} and {first[key][0]} record the same point (same config and seed) with different "
                "results: keep one of them (a second record is not another seed)"
            )
    return kept, dropped
