"""How many torch threads a run uses, and whether the machine gives them the CPU time they need.

torch's default is one thread per core. On a machine other jobs keep busy that oversubscribes the cores, and a
learner update gets many times slower (docs/TRAINING.md, "Threads"). ``threads=auto``, the default, takes the
cores the load average leaves free; an integer fixes the count and ``0`` keeps torch's default.
:class:`SpeedCheck` measures once, after :data:`WINDOW_S` seconds of training, how long the threads waited for
a CPU, and warns when the machine is oversubscribed.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

AUTO = "auto"
#: Seconds of training after which the CPU share is measured (once).
WINDOW_S = 30.0
#: Warn when the process's threads spent more than this share of their runnable time waiting for a core.
MAX_WAIT_SHARE = 1 / 3
#: Without scheduler statistics: warn below this many CPU-seconds per wall second (the training loop
#: always keeps one thread busy, so a quiet machine gives about 1 or more).
MIN_CPU_SHARE = 0.5

log = logging.getLogger(__name__)


def threads_problem(value: object, cores: int) -> str | None:
    """Why ``threads=value`` cannot be used, or None: it must be ``auto`` or an integer 0..cores."""
    text = str(value).strip()
    if text == AUTO:
        return None
    allowed = f"{AUTO} (the cores the load leaves free), 0 (torch's default: one per core) or 1 to {cores}"
    if not text.isdigit():
        return f"allowed values are {allowed}"
    if int(text) > cores:
        return f"this machine has {cores} CPU cores: use {allowed}"
    return None


def auto_threads(cores: int, load: float) -> int:
    """The cores the 1-minute load average leaves free, rounded, between 1 and ``cores``."""
    return max(1, min(cores, int(cores - load + 0.5)))


def load_average() -> float:
    """The 1-minute load average (0 where the platform has none)."""
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):
        return 0.0


def resolve_threads(value: object, cores: int, load: float) -> int:
    """The torch thread count for ``threads=value``: 0 means torch's default (left as it is)."""
    text = str(value).strip()
    return auto_threads(cores, load) if text == AUTO else int(text)


def apply_threads(value: object) -> int:
    """Set torch's thread count for ``threads=value`` (0 leaves torch's default); returns the count used."""
    import torch  # here: the config's checks of threads= must not load torch

    threads = resolve_threads(value, cpu_count(), load_average())
    if threads:
        torch.set_num_threads(threads)
    return torch.get_num_threads()


def scheduler_times() -> tuple[float, float] | None:
    """Seconds this process's threads ran on a CPU and waited for one (Linux ``schedstat``), or None."""
    ran = waited = 0.0
    try:
        for task in Path("/proc/self/task").iterdir():
            fields = (task / "schedstat").read_text().split()
            ran, waited = ran + int(fields[0]) / 1e9, waited + int(fields[1]) / 1e9
    except (OSError, ValueError, IndexError):
        return None
    return ran, waited


def oversubscription(
    wall_s: float, cpu_s: float, wait_s: float | None, threads: int, load: float, cores: int
) -> str | None:
    """The warning for a measurement window, or None when the run got its CPU time; ``wait_s`` None means
    unknown, and then the CPU share decides."""
    if wall_s <= 0:
        return None
    if wait_s is not None:
        share = wait_s / max(wait_s + cpu_s, 1e-9)
        if share <= MAX_WAIT_SHARE:
            return None
        what = f"this run's threads waited for a CPU {share:.0%} of the time"
    else:
        share = cpu_s / wall_s
        if share >= MIN_CPU_SHARE:
            return None
        what = f"this run got {share:.2f} CPU-seconds per second"
    advice = "threads=1" if threads > 1 else "fewer jobs at a time on this machine"
    return (
        f"the machine is oversubscribed: over the first {wall_s:.0f} s {what} (load average {load:.1f} on "
        f"{cores} cores, threads={threads}); training runs slower than on a quiet machine: use {advice}"
    )


class SpeedCheck:
    """Measures the first :data:`WINDOW_S` seconds of training once and logs :func:`oversubscription`'s
    warning. Off for a multiprocess collector, whose workers' time is not this process's."""

    def __init__(self, threads: int, enabled: bool = True, window_s: float = WINDOW_S, decide=None) -> None:
        self.threads, self.window_s = threads, window_s
        self.decide = decide or oversubscription  # (wall_s, cpu_s, wait_s, threads, load, cores) -> warning
        self.done = not enabled
        self.warning: str | None = None
        self._start = (time.monotonic(), time.process_time(), scheduler_times())

    def observe(self) -> None:
        """Call once per batch; cheap until the window is over, then measures once."""
        if self.done:
            return
        wall = time.monotonic() - self._start[0]
        if wall < self.window_s:
            return
        self.done = True
        cpu = time.process_time() - self._start[1]
        before, now = self._start[2], scheduler_times()
        wait = None
        if before is not None and now is not None:
            cpu, wait = now[0] - before[0], now[1] - before[1]

        self.warning = self.decide(wall, cpu, wait, self.threads, load_average(), cpu_count())
        if self.warning:
            log.warning(self.warning)


def cpu_count() -> int:
    """CPU cores this process may run on, from its affinity (Slurm, taskset)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1
