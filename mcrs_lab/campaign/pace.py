"""How long a campaign point will take, read off the pace of the training runs already recorded.

The campaign's own records (``<records>/<experiment>/<budget>/*.json``) come first; where they hold no run
of a point's algorithm on its map, the records of older campaigns kept deeper in the same folder (the
"near" campaign's ``near/<experiment>/<budget>/``) answer, then those of the campaign whose folder holds
this one (the lured campaign's ``results/records/<experiment>/<budget>/`` beside the paper's
``results/records/paper``), since the simulator's and the learner's cost do not depend on the reward's
reading. A pace is env steps per second of wall time over a run's sessions, evaluations and checkpoints
included, as ``mcrs-campaign run`` will spend it, for a run of one torch thread: a record of a run with
more threads is brought down to one by :func:`thread_speedup`, and :meth:`Pace.speed` brings it up to the
threads asked for.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from mcrs_lab.analysis.records import RecordError
from mcrs_lab.analysis.runs import read_record

#: (map, algorithm) -> env steps per second of a 1-thread run, averaged over the recorded runs.
Speeds = dict[tuple[str, str], float]
#: One 2-thread run's env steps per second over those of one of two 1-thread runs side by side, measured
#: by ``mcrs-bench-learner --launcher-steps`` (docs/PERFORMANCE.md, "Figures behind constants").
TWO_THREAD_SPEEDUP = 1.47


def thread_speedup(threads: int) -> float:
    """How much faster a run of ``threads`` torch threads goes than a 1-thread run beside another: measured
    for 2; more threads are counted as 2 (no figure for them: an estimate errs long, not short)."""
    return 1.0 if threads <= 1 else TWO_THREAD_SPEEDUP


def _speeds_of(paths: Iterable[Path]) -> Speeds:
    """The mean speed per (map, algorithm) of the training records in ``paths``; a file that is not a valid
    record gives no speed (the tools that read it as evidence refuse it by name)."""
    per: dict[tuple[str, str], list[float]] = {}
    for path in paths:
        try:
            record = read_record(path)
        except RecordError:
            continue
        if not record or record.get("kind") != "training":
            continue
        seconds = sum(s.get("wall_s", 0.0) for s in record.get("sessions", [])) or record.get("loop_time_s")
        steps = record.get("checkpoint_env_steps") or 0
        if seconds and steps:
            key = (record["config"]["env"]["name"], record["config"]["algo"]["name"])
            threads = record["config"].get("threads")
            per.setdefault(key, []).append(
                steps / seconds / thread_speedup(threads if isinstance(threads, int) else 1)
            )
    return {key: sum(values) / len(values) for key, values in per.items()}


@dataclass(frozen=True)
class Pace:
    """The recorded speeds: ``own`` of the campaign's folders, ``older`` of every training record below,
    ``outer`` of the campaign whose folder holds this one (its ``*/*/*.json`` only, never a whole tree)."""

    own: Speeds
    older: Speeds
    outer: Speeds

    @classmethod
    def read(cls, records: Path) -> Pace:
        own = sorted(records.glob("*/*/*.json"))
        below = set(records.rglob("*.json"))
        outer = sorted(set(records.parent.glob("*/*/*.json")) - below) if records.parent != records else []
        return cls(_speeds_of(own), _speeds_of(sorted(below - set(own))), _speeds_of(outer))

    def speed(self, env: str, algo: str, threads: int = 1) -> float | None:
        """Env steps per second of a run of ``algo`` on ``env`` with ``threads`` torch threads: that
        algorithm's own runs (this campaign's, older ones, the outer campaign's), else the slowest recorded
        algorithm on that map (an algorithm's first run would otherwise look free); None when no run on that
        map is recorded."""
        tiers = (self.own, self.older, self.outer)
        for speeds in tiers:
            if (env, algo) in speeds:
                return speeds[env, algo] * thread_speedup(threads)
        for speeds in tiers:
            same_map = [value for (name, _), value in speeds.items() if name == env]
            if same_map:
                return min(same_map) * thread_speedup(threads)
        return None


@dataclass
class MachinePace:
    """How the runs of this machine compare with the recorded pace, which other machines may have set (one
    CPU model string has trained EMC on map20 at 145 and at 88 env steps/s): each run started here and
    finished gives its wall time over its estimate. A next start is scaled by the mean ratio of its own
    (map, algorithm), since each one's recorded pace may come from another machine (map10 QPLEX took 1.37x
    and CNN-SEMU 1.05x here side by side), or by the mean over all where none of its kind has finished. A
    faster machine keeps the recorded estimates (an estimate errs long, not short)."""

    ratios: dict[tuple[str, str], list[float]] = field(default_factory=dict)

    def observe(self, kind: tuple[str, str], estimated_s: float | None, wall_s: float) -> None:
        """A run of ``kind`` (map, algorithm) estimated at ``estimated_s`` seconds took ``wall_s``."""
        if estimated_s and estimated_s > 0 and wall_s > 0:
            self.ratios.setdefault(kind, []).append(wall_s / estimated_s)

    def factor(self, kind: tuple[str, str] | None = None) -> float:
        """The scale of a start of ``kind``: its own runs' mean ratio, else all runs', at least 1."""
        pool = self.ratios.get(kind) if kind is not None else None
        pool = pool or [ratio for ratios in self.ratios.values() for ratio in ratios]
        return max(1.0, sum(pool) / len(pool)) if pool else 1.0

    def scale(self, estimate_s: float | None, kind: tuple[str, str] | None = None) -> float | None:
        return None if estimate_s is None else estimate_s * self.factor(kind)


def left_line(estimates: list[float | None], jobs: int) -> str:
    """One line on the time the runs of ``estimates`` (seconds each; None: unknown) still need."""
    known = [seconds for seconds in estimates if seconds is not None]
    hours = sum(known) / 3600
    line = f"left: about {hours:.1f} h of runs at the recorded runs' pace ({hours / jobs:.1f} h at {jobs} at a time)"
    if len(known) < len(estimates):
        line += f"; {len(estimates) - len(known)} runs have no estimate (no timed run on their map)"
    return line
