"""Where each campaign point stands, read from the disk alone: its record and its run directory.

- ``done``: a record of a finished run at the budget's length;
- ``unrecorded``: the run finished but has no record yet (``mcrs-campaign run`` records it first);
- ``partial``: a run directory with ``checkpoints/last.pt`` short of the budget, or at it without its final
  evaluation (killed after its last batch): resumable;
- ``missing``: nothing to resume (a record of a stopped run elsewhere is only noted).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from mcrs.experiment.run import checkpoint as ckpt
from mcrs_lab.analysis.runs import read_record
from mcrs_lab.campaign.matrix import Point

STATES = ("done", "unrecorded", "partial", "missing")


@dataclass(frozen=True)
class Progress:
    point: Point
    state: str
    env_steps: int  # reached: by the record (done) or the checkpoint (partial, unrecorded); 0 if missing
    note: str = ""  # the record (done), the run directory (partial, unrecorded), an earlier record (missing)


def checkpoint_steps(run_dir: Path) -> tuple[int | None, bool]:
    """The env steps in ``run_dir``'s ``last.pt`` (mapped, not read: it holds the replay), or None, and
    whether it still awaits its final evaluation (a kill after its last batch: resumed, not recorded)."""
    path = ckpt.checkpoint_path(run_dir)
    if not path.is_file():
        return None, False
    try:
        state = ckpt.load(path, mmap=True)
        return int(state["counters"]["env_steps"]), ckpt.awaits_final_evaluation(state)
    except (ckpt.CheckpointError, KeyError, TypeError, ValueError):
        return None, False


def progress(point: Point, outputs: Path, records: Path, total_env_steps: int) -> Progress:
    record = read_record(point.record_path(records)) if point.record_path(records).is_file() else None
    if record is not None and record.get("status") == "finished":
        steps = int(record.get("checkpoint_env_steps") or 0)
        if steps >= total_env_steps:
            return Progress(point, "done", steps, f"record of {record.get('run_dir')}")
    run_dir = point.run_dir(outputs)
    steps, awaiting = checkpoint_steps(run_dir)
    if steps is not None and steps >= total_env_steps and not awaiting:
        return Progress(point, "unrecorded", steps, str(run_dir))
    if steps is not None:
        return Progress(point, "partial", steps, str(run_dir))
    note = ""
    if record is not None:
        status, reached = record.get("status"), record.get("checkpoint_env_steps")
        note = f"a {status} record at {reached} steps of {record.get('run_dir')}"
    return Progress(point, "missing", 0, note)
