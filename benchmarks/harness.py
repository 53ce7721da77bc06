"""The skeleton every ``mcrs-bench-*`` command shares: common arguments, machine facts, results as data.

Why: a benchmark's figures are quoted in docs and issues and checked by tests. Printed text alone is
for people; regex-parsing it is brittle, and a figure that silently disappeared would go unnoticed. So
each command records its figures in a :class:`Report` (named values with units, goals and a PASS/FAIL
verdict) and tables of rows, prints its usual human lines from those same values, and writes the report
as JSON: to ``--json PATH``, or by default to ``outputs/benchmarks/<command>-<time>-<pid>.json`` (the
path is printed last; ``--json none`` writes nothing).

A command is three pieces: :func:`make_parser` (adds ``--threads``, ``--json`` and optionally
``--quick``), a body ``run(args, report)`` that measures, prints and records, and
:func:`run_benchmark` that ties them together (threads set and restored, TorchRL's INFO lines silenced,
load average taken before and after, the JSON written)::

    def main(argv=None):
        return run_benchmark(_parser(), argv, _run)
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import os
import platform
import shlex
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from mcrs_benchmarks.common import benchmark_process, load_average, pass_fail

SCHEMA = 1  # bump when the JSON layout changes incompatibly
DEFAULT_DIR = Path("outputs") / "benchmarks"
NO_JSON = "none"
_OPS: dict[str, Callable[[float, float], bool]] = {
    "<=": lambda v, limit: v <= limit,
    "<": lambda v, limit: v < limit,
    ">=": lambda v, limit: v >= limit,
    ">": lambda v, limit: v > limit,
}

Value = float | int | bool | str | None


@dataclass(frozen=True)
class Goal:
    """A target a figure is judged against, e.g. ``Goal("<=", 1.15)``."""

    op: str
    limit: float

    def __post_init__(self) -> None:
        if self.op not in _OPS:
            raise ValueError(f"Goal op must be one of {sorted(_OPS)}, got {self.op!r}")

    def met(self, value: float) -> bool:
        return _OPS[self.op](float(value), self.limit)

    def __str__(self) -> str:
        return f"{self.op} {self.limit:g}"


@dataclass
class Figure:
    """One named result. ``passed`` is None when there is no goal or it is not judged (``not_judged`` says
    why, e.g. a smoke-test size); ``valid=False`` marks a comparison that is void (it then FAILs)."""

    name: str
    value: Value
    unit: str = ""
    goal: Goal | None = None
    not_judged: str = ""
    valid: bool = True
    note: str = ""

    @property
    def passed(self) -> bool | None:
        if self.goal is None or self.not_judged:
            return None
        if self.value is None or not self.valid:
            return False
        if isinstance(self.value, float) and math.isnan(self.value):
            return False
        return self.goal.met(self.value)  # type: ignore[arg-type]

    @property
    def verdict(self) -> str:
        """ "PASS", "FAIL" or "not judged (why)": the words the printed lines use."""
        if self.not_judged:
            return f"not judged ({self.not_judged})"
        passed = self.passed
        return "n/a" if passed is None else pass_fail(passed)

    def as_json(self) -> dict[str, Any]:
        value = self.value
        if isinstance(value, float) and not math.isfinite(value):
            value = None  # JSON has no NaN/inf
        return {
            "value": value,
            "unit": self.unit,
            "goal": None if self.goal is None else str(self.goal),
            "passed": self.passed,
            "not_judged": self.not_judged or None,
            "valid": self.valid,
            "note": self.note or None,
        }


def machine_facts() -> dict[str, Any]:
    """What the figures depend on besides the code: cores, load, torch build and threads, commit."""
    try:
        load = [round(x, 2) for x in os.getloadavg()]
    except OSError:
        load = None
    return {
        "cpus": os.cpu_count(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "cuda": torch.cuda.is_available(),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "load_average": load,  # 1, 5 and 15 minutes
        "git_commit": _git_commit(),
    }


def _git_commit() -> str | None:
    """The commit of the checkout ``mcrs`` runs from, or None outside a git checkout."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=5,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return (out.stdout.strip() or None) if out.returncode == 0 else None


@dataclass
class Report:
    """Everything one benchmark run measured, printable and serialisable."""

    benchmark: str
    command: str
    arguments: dict[str, Any]
    figures: dict[str, Figure] = field(default_factory=dict)
    tables: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    machine_before: dict[str, Any] = field(default_factory=dict)
    load_after: list[float] | None = None
    started: str = ""
    seconds: float = 0.0

    def figure(
        self,
        name: str,
        value: Value,
        unit: str = "",
        goal: Goal | None = None,
        *,
        not_judged: str = "",
        valid: bool = True,
        note: str = "",
    ) -> Figure:
        """Record (or replace) the figure ``name`` and return it, so that its verdict can be printed."""
        fig = Figure(name, value, unit, goal, not_judged, valid, note)
        self.figures[name] = fig
        return fig

    def row(self, table: str, **values: Value) -> None:
        """Append one row to ``table`` (the printed tables, as lists of dicts)."""
        self.tables.setdefault(table, []).append(values)

    def header(self, title: str, device: str = "cpu", details: str = "") -> None:
        """Print the first two lines every benchmark starts with: what, where, how loaded; the command."""
        print(
            f"MCRS {title}: {details}device={device}, torch threads={torch.get_num_threads()}, "
            f"cpus={os.cpu_count()}, load average {load_average()}\ncommand: {self.command}",
            flush=True,
        )

    @property
    def passed(self) -> bool | None:
        """All judged figures passed (None: nothing was judged)."""
        verdicts = [f.passed for f in self.figures.values() if f.passed is not None]
        return all(verdicts) if verdicts else None

    def as_json(self) -> dict[str, Any]:
        return {
            "schema": SCHEMA,
            "benchmark": self.benchmark,
            "command": self.command,
            "started": self.started,
            "seconds": round(self.seconds, 3),
            "machine": {**self.machine_before, "load_average_after": self.load_after},
            "arguments": self.arguments,
            "passed": self.passed,
            "figures": {name: fig.as_json() for name, fig in self.figures.items()},
            "tables": self.tables,
        }

    def write(self, path: Path) -> Path:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.as_json(), indent=2, allow_nan=False) + "\n")
        return path


def make_parser(
    prog: str, description: str, *, threads: int = 0, quick: str | None = None
) -> argparse.ArgumentParser:
    """A parser with the arguments every benchmark takes: ``--threads``, ``--json`` and, when ``quick``
    is its help text, ``--quick``."""
    parser = argparse.ArgumentParser(prog=prog, description=description)
    parser.add_argument(
        "--threads",
        type=int,
        default=threads,
        help=f"torch intra-op threads (0: torch's default; default {threads})",
    )
    parser.add_argument(
        "--json",
        default=None,
        metavar="PATH",
        help=f"write the results as JSON to PATH (default: {DEFAULT_DIR}/{prog}-<time>-<pid>.json; "
        f"'{NO_JSON}': do not write)",
    )
    if quick is not None:
        parser.add_argument("--quick", action="store_true", help=quick)
    return parser


def require_at_least(
    parser: argparse.ArgumentParser, args: argparse.Namespace, minimum: float, *names: str
) -> None:
    """Exit with one line naming the argument when ``args.<name>`` (a number or a list) is below ``minimum``."""
    for name in names:
        value = getattr(args, name)
        values = value if isinstance(value, list) else [value]
        if any(v < minimum for v in values):
            parser.error(f"--{name.replace('_', '-')} must be >= {minimum:g}, got {value}")


def default_json_path(prog: str) -> Path:
    stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    return DEFAULT_DIR / f"{prog}-{stamp}-{os.getpid()}.json"


def run_benchmark(
    parser: argparse.ArgumentParser,
    argv: Sequence[str] | None,
    body: Callable[[argparse.Namespace, Report], None],
    validate: Callable[[argparse.ArgumentParser, argparse.Namespace], None] | None = None,
) -> int:
    """Parse ``argv``, run ``body(args, report)`` with ``args.threads`` torch threads, write the JSON.

    ``--threads`` below 0 is refused here; ``validate`` checks the command's own arguments. The exit
    status is 0 whatever the verdicts: a FAIL is a finding, not an error of the command.
    """
    prog = parser.prog
    command = shlex.join([prog, *(sys.argv[1:] if argv is None else argv)])
    args = parser.parse_args(argv)
    require_at_least(parser, args, 0, "threads")
    if validate is not None:
        validate(parser, args)
    arguments = {k: v for k, v in vars(args).items() if k != "json"}
    report = Report(prog, command, arguments)
    with benchmark_process(args.threads):
        report.started = dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")
        report.machine_before = machine_facts()
        start = time.perf_counter()
        body(args, report)
        report.seconds = time.perf_counter() - start
        try:
            report.load_after = [round(x, 2) for x in os.getloadavg()]
        except OSError:
            report.load_after = None
    if args.json != NO_JSON:
        path = report.write(Path(args.json) if args.json else default_json_path(prog))
        print(f"\nresults as JSON: {path}", flush=True)
    return 0
