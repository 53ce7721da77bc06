"""A Hydra sweep's progress and summary (``hydra.callbacks.sweep_progress`` of ``mcrs-train`` and
``mcrs-eval``): after each job, one line on the console::

    mcrs-train sweep: 2 of 6 done, elapsed 0:24:10, ETA 0:48:20; job 1 (seed=1): reward 12.31

and at the end a table with one row per job, printed and written to ``<sweep dir>/sweep_summary.md``.

A launcher may run jobs in other processes, where the callback is a copy, so each job writes its row under
``<sweep dir>/.sweep/`` and counts the rows there. Every row rewrites the table, so a sweep that stops on a
failed job still has it. The job count is the basic sweeper's; with another sweeper only the jobs done are
counted.
"""

from __future__ import annotations

import csv
import json
import time
from pathlib import Path
from typing import Any

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from mcrs.experiment.util.atomic import write_text_atomic
from mcrs.experiment.util.tables import markdown

#: Where the rows live inside the sweep directory, and the table's file.
STATE_DIR = ".sweep"
SUMMARY = "sweep_summary.md"
START = "start.json"
COLUMNS = ["job", "overrides", "episode reward", "no-fly violations", "wall time", "status"]


class SweepProgress(Callback):
    """The Hydra callback: notes the sweep's start and job count, times each job in its own process, writes
    its row and prints the progress line, and prints the table at the end. Outside a multirun it does nothing.
    """

    def __init__(self, command: str = "mcrs") -> None:
        self.command = command
        self._job_start: float | None = None

    # ------------------------------------------------------------------ Hydra's hooks
    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        state = _state_dir(config)
        state.mkdir(parents=True, exist_ok=True)
        write_text_atomic(state / START, json.dumps({"start": time.time(), "jobs": sweep_size(config)}))

    def on_job_start(self, config: DictConfig, **kwargs: Any) -> None:
        self._job_start = time.monotonic()

    def on_job_end(self, config: DictConfig, job_return: Any, **kwargs: Any) -> None:
        if not _multirun(config):
            return
        state = _state_dir(config)
        num = int(OmegaConf.select(config, "hydra.job.num", default=0) or 0)
        output_dir = Path(str(OmegaConf.select(config, "hydra.runtime.output_dir", default=".")))
        status = getattr(getattr(job_return, "status", None), "name", "UNKNOWN")
        value = getattr(job_return, "_return_value", None)
        reward, no_fly = job_results(output_dir, value if status == "COMPLETED" else None)
        row = {
            "job": num,
            "overrides": list(getattr(job_return, "overrides", None) or []),
            "reward": reward,
            "no_fly": no_fly,
            "wall_s": time.monotonic() - self._job_start if self._job_start is not None else None,
            "status": "done" if status == "COMPLETED" else "failed",
            "error": _one_line(value) if status == "FAILED" else None,
            "output_dir": str(output_dir),
        }
        state.mkdir(parents=True, exist_ok=True)
        write_text_atomic(state / f"job_{num:05d}.json", json.dumps(row))
        rows, start = read_rows(state), read_start(state)
        write_summary(state.parent, rows)
        print(f"{self.command} sweep: {progress_line(rows, start)}; {_row_line(row)}", flush=True)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        state = _state_dir(config)
        rows, start = read_rows(state), read_start(state)
        if not rows:
            return
        path = write_summary(state.parent, rows)
        print(
            f"{self.command} sweep finished: {progress_line(rows, start, final=True)}\n\n"
            f"{summary_table(rows)}\n\nsummary: {path}",
            flush=True,
        )


# ---------------------------------------------------------------------------------------- the rows
def sweep_jobs(config: DictConfig) -> list[list[str]] | None:
    """Each job's overrides as the basic sweeper makes them, or None for another sweeper or unreadable
    overrides."""
    target = str(OmegaConf.select(config, "hydra.sweeper._target_", default="") or "")
    if not target.endswith("BasicSweeper"):
        return None
    try:
        from hydra._internal.core_plugins.basic_sweeper import BasicSweeper  # private: may fail

        params = OmegaConf.select(config, "hydra.sweeper.params", default=None) or {}
        arguments = [f"{k}={v}" for k, v in params.items()]
        arguments += list(OmegaConf.select(config, "hydra.overrides.task", default=None) or [])
        overrides = OverridesParser.create().parse_overrides(arguments)
        return [list(job) for batch in BasicSweeper.split_arguments(overrides, None) for job in batch]
    except Exception:  # the list is a nicety (the count, the early check): unreadable, it is unknown
        return None


def sweep_size(config: DictConfig) -> int | None:
    """How many jobs the basic sweeper makes, or None when that is unknown."""
    jobs = sweep_jobs(config)
    return None if jobs is None else len(jobs)


def job_results(output_dir: Path, returned: Any = None) -> tuple[str, str]:
    """The job's final episode reward and no-fly violations as table cells, from an ``mcrs-train`` run's last
    ``eval/`` scalars, an ``mcrs-eval`` ``metrics.csv``, or the job's return value."""
    scalars = output_dir / "logs" / "scalars" / "eval"
    if (scalars / "episode_reward.csv").is_file():
        return _last_scalar(scalars / "episode_reward.csv"), _last_scalar(scalars / "no_fly_violations.csv")
    metrics = output_dir / "metrics.csv"
    if metrics.is_file():
        try:
            with open(metrics, newline="") as f:
                rows = list(csv.DictReader(f))
        except (OSError, csv.Error):
            rows = []
        if rows:

            def cell(column: str) -> str:
                values = [_number(r.get(column)) for r in rows]
                if len(rows) == 1:
                    return values[0]
                return ", ".join(
                    f"{Path(str(r.get('policy'))).name} {v}" for r, v in zip(rows, values, strict=True)
                )

            return cell("episode_reward_mean"), cell("no_fly_violations_mean")
    if isinstance(returned, (int, float)) and not isinstance(returned, bool):
        return _number(returned), ""
    return "", ""


def read_rows(state: Path) -> list[dict[str, Any]]:
    rows = []
    for path in sorted(state.glob("job_*.json")):
        try:
            rows.append(json.loads(path.read_text()))
        except (OSError, ValueError):
            continue  # being replaced by its writer: the next line counts it
    return sorted(rows, key=lambda r: int(r.get("job", 0)))


def read_start(state: Path) -> dict[str, Any]:
    try:
        start = json.loads((state / START).read_text())
    except (OSError, ValueError):
        return {}
    return start if isinstance(start, dict) else {}


def progress_line(rows: list[dict[str, Any]], start: dict[str, Any], final: bool = False) -> str:
    """``2 of 6 done (1 failed), elapsed 0:24:10, ETA 0:48:20``; the ETA is the mean time per job so far times
    the jobs left."""
    total = start.get("jobs")
    done = len(rows)
    failed = sum(1 for r in rows if r.get("status") != "done")
    text = f"{done} of {total} done" if isinstance(total, int) else f"{done} done"
    if failed:
        text += f" ({failed} failed)"
    began = start.get("start")
    if isinstance(began, (int, float)):
        elapsed = max(time.time() - began, 0.0)
        text += f", elapsed {clock(elapsed)}"
        if not final and isinstance(total, int) and 0 < done < total:
            text += f", ETA {clock(elapsed / done * (total - done))}"
    return text


def summary_table(rows: list[dict[str, Any]]) -> str:
    """The markdown table, one row per job; the overrides all jobs share are said once above it."""
    lists = [list(r.get("overrides") or []) for r in rows]
    common = [o for o in lists[0] if all(o in other for other in lists[1:])] if len(lists) > 1 else []
    body = []
    for row, overrides in zip(rows, lists, strict=True):
        own = [o for o in overrides if o not in common]
        status = row.get("status", "")
        if row.get("error"):
            status = f"{status}: {row['error']}"
        wall = row.get("wall_s")
        body.append([
            str(row.get("job", "")), " ".join(own) or "-", row.get("reward") or "-", row.get("no_fly") or "-",
            clock(wall) if isinstance(wall, (int, float)) else "-", status,
        ])  # fmt: skip
    table = markdown(COLUMNS, body, left=len(COLUMNS))
    return (f"every job: {' '.join(common)}\n\n" if common else "") + table


def write_summary(sweep_dir: Path, rows: list[dict[str, Any]]) -> Path:
    path = sweep_dir / SUMMARY
    write_text_atomic(path, f"# Sweep summary\n\n{summary_table(rows)}\n")
    return path


def clock(seconds: float) -> str:
    """``1:02:03`` or ``2:03``."""
    seconds = round(seconds)
    hours, rest = divmod(seconds, 3600)
    minutes, secs = divmod(rest, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}" if hours else f"{minutes}:{secs:02d}"


# ---------------------------------------------------------------------------------------- helpers
def _state_dir(config: DictConfig) -> Path:
    return Path(str(OmegaConf.select(config, "hydra.sweep.dir", default="."))) / STATE_DIR


def _multirun(config: DictConfig) -> bool:
    mode = OmegaConf.select(config, "hydra.mode", default=None)
    return mode == RunMode.MULTIRUN or str(mode) in ("MULTIRUN", "RunMode.MULTIRUN")


def _row_line(row: dict[str, Any]) -> str:
    overrides = " ".join(row.get("overrides") or [])
    what = f"job {row.get('job')} ({overrides})" if overrides else f"job {row.get('job')}"
    if row.get("status") != "done":
        return f"{what}: failed{': ' + row['error'] if row.get('error') else ''}"
    return f"{what}: reward {row['reward']}" if row.get("reward") else f"{what}: done"


def _last_scalar(path: Path) -> str:
    try:
        lines = [line for line in path.read_text(errors="replace").splitlines() if line.strip()]
        return _number(lines[-1].split(",")[-1]) if lines else ""
    except (OSError, IndexError):
        return ""


def _number(value: Any) -> str:
    try:
        return f"{float(value):.2f}"
    except (TypeError, ValueError):
        return ""


def _one_line(error: Any) -> str:
    text = str(error).strip().splitlines()
    return (text[0] if text else type(error).__name__)[:200]
