"""Running the campaign's points on one machine: a few ``mcrs-train`` processes at a time, partial runs
resumed first, no new start that the time budget cannot hold, a record of every run that ends.

With ``fill`` the budget is a hard stop instead: every slot is kept busy until shortly before it, and the
runs still going at the deadline are stopped as on SIGINT (checkpointed, recorded as stopped, resumed
first by the next ``run``), so that a working session that ends at a known time loses no core-hours.
With ``finish_first`` too, a freed slot takes the first run expected to end before the deadline (partial
runs still resume first), then the rest: on a machine that may not keep its run folders between sessions,
a run stopped at the deadline can be lost with them. With ``finish_only`` the rest are not started at all:
a slot that no run can fill in time stays free (for the session's own work) instead of training a run that
the deadline would stop and the machine then lose. Those choices use the recorded pace, scaled once a
run started here has finished by how much longer than its estimate it took, per map and algorithm where
one of them has finished (pace.MachinePace): the records may come from a faster machine.

Each child runs in its own session (process group), with one torch thread (``threads``: more), its output appended to
``<run dir>/campaign.log``; each session is noted in ``<run dir>/campaign.jsonl`` (times, command,
exit status, commit, machine). On SIGINT or SIGTERM the children get SIGINT, are waited for, and are
recorded as stopped: their last checkpoint stays, and the next ``run`` resumes them. A run that
finishes is then evaluated as the campaign file's ``evaluations:`` ask (mcrs_lab.campaign.evaluations),
while the other jobs go on. Where a ``tsne:`` entry samples a finished run's episodic memory, its states
are recorded before the run is pruned, and the t-SNE once its embedding runs have finished too
(mcrs_lab.campaign.figure9).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import shlex
import signal
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.run.rundir import lock_holder
from mcrs_lab.analysis.records import (
    SESSIONS,
    RecordError,
    git_facts,
    loop_time_s,
    machine_facts,
    make_record,
    write_record,
)
from mcrs_lab.campaign import figure9
from mcrs_lab.campaign.evaluations import Evaluation, plan, run_pending
from mcrs_lab.campaign.matrix import Point
from mcrs_lab.campaign.pace import MachinePace, Pace, left_line
from mcrs_lab.campaign.progress import Progress, progress

#: Seconds a stopped child may take to exit after SIGINT before it is killed.
STOP_GRACE_S = 120.0
#: With ``fill``: no start with less time than this left before the deadline (a run's set-up, its
#: first evaluation and its checkpoint would be most of it).
FILL_FLOOR_S = 600.0
#: No t-SNE (figure 9) with less time than this left before the deadline: at one thread beside two runs, a
#: 20k-state panel took 385 s here, four panels about half an hour; a later run makes it.
TSNE_FLOOR_S = 3600.0
LOG = "campaign.log"
#: Under the records folder: one lock file per point being trained, shared by every runner that records
#: there (the lock per outputs folder cannot see a runner with other --outputs).
CLAIMS = ".claims"


@dataclass
class Job:
    """A running ``mcrs-train`` child."""

    point: Point
    command: list[str]
    process: subprocess.Popen
    log: IO[str]
    claim: IO[str]  # the point's lock (claim_point), shared with the child
    started: float = field(default_factory=time.time)
    machine: dict[str, Any] = field(default_factory=machine_facts)
    estimate_s: float | None = None  # a fresh start's estimate at the recorded pace (MachinePace)


def _hours(seconds: float | None) -> str:
    return "unknown" if seconds is None else f"{seconds / 3600:.2f} h"


def _print(*parts: object) -> None:
    print(*parts, flush=True)


def claim_path(records: Path, point: Point) -> Path:
    return records / CLAIMS / f"{point.id.replace('/', '--')}.lock"


def claim_point(records: Path, point: Point, outputs: Path) -> IO[str] | str:
    """Hold ``point`` while this process trains it: the open lock file, or, when another process holds
    it, who that is. Two runners recording into one folder with different ``--outputs`` would otherwise
    both train it. The child inherits the handle, so the hold lasts as long as the run, whatever becomes of
    the runner; closing it in every process that has it lets the point go."""
    path = claim_path(records, point)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle = open(path, "a+")  # noqa: SIM115 (kept open while the point trains)
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.seek(0)
        holder = handle.read().strip() or "a process"
        handle.close()
        return holder
    handle.seek(0)
    handle.truncate()
    handle.write(f"pid {os.getpid()}, outputs {outputs.resolve()}")
    handle.flush()
    return handle


def claim_holder(records: Path, point: Point) -> str | None:
    """Who holds ``point`` now (``"pid 7438, outputs /work/o"``), or None; creates nothing."""
    try:
        fd = os.open(claim_path(records, point), os.O_RDWR)
    except OSError:  # no claim file: never claimed
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return os.pread(fd, 300, 0).decode(errors="replace").strip() or "a process"
    finally:
        os.close(fd)  # closing drops a lock taken here
    return None


def _next_run(
    queue: list[tuple[tuple[Progress, list[str]], float | None]], left: float, finish_first: bool
) -> int:
    """The index in ``queue`` ((launch, its estimate in seconds) pairs, in the plan's order) of the run to
    start with ``left`` seconds to the deadline: the first, or with ``finish_first`` the first that resumes a
    partial run or is expected to end in time (none: the first)."""
    if finish_first:
        for index, ((state, _), estimate) in enumerate(queue):
            if state.state == "partial" or (estimate is not None and estimate <= left):
                return index
    return 0


class CampaignBusy(RuntimeError):
    """Another ``mcrs-campaign run`` holds the outputs folder."""


class Campaign:
    """The points to run, where their runs and records go, and how many run at once."""

    def __init__(
        self,
        points: list[Point],
        outputs: Path,
        records: Path,
        total_env_steps: int,
        jobs: int = 2,
        prune: bool = True,
        evaluations: list[Evaluation] | None = None,
        threads: int = 1,
        tsne: list[figure9.TsneEntry] | None = None,
        make_tsne: bool = True,
    ) -> None:
        self.points, self.outputs, self.records = points, outputs, records
        self.total, self.jobs, self.prune, self.threads = total_env_steps, jobs, prune, threads
        self.evaluations = evaluations or []
        # the states of a tsne entry are always sampled before pruning; the t-SNE itself with make_tsne
        self.tsne, self.make_tsne = tsne or [], make_tsne
        self.stop_signal: int | None = None
        self.deadline = float("inf")  # set by run
        self.failed = 0  # runs of this campaign that ended with a non-zero exit status (not stopped by it)

    def status(self) -> list[Progress]:
        return [progress(p, self.outputs, self.records, self.total) for p in self.points]

    def plan(self) -> tuple[list[Progress], list[tuple[Progress, list[str]]]]:
        """Runs to record now (finished, no record), then the launches in order: partial runs first
        (resumed), then missing ones, each in the campaign file's order."""
        states = self.status()
        to_record = [s for s in states if s.state == "unrecorded"]
        launches = [
            (s, s.point.resume_command(self.outputs, self.total, self.threads))
            for s in states
            if s.state == "partial"
        ]
        launches += [
            (s, s.point.train_command(self.outputs, self.threads)) for s in states if s.state == "missing"
        ]
        return to_record, launches

    # -------------------------------------------------------------------------------- estimates
    def estimate_s(self, state: Progress, pace: Pace) -> float | None:
        """Seconds left for a point: its own speed so far (a partial run), else the recorded runs' pace
        (mcrs_lab.campaign.pace); None when no run on its map is recorded."""
        speed = pace.speed(state.point.env, state.point.algo, self.threads)
        if state.state == "partial":
            seconds = loop_time_s(state.point.run_dir(self.outputs))
            if seconds and state.env_steps:
                speed = state.env_steps / seconds
        return (self.total - state.env_steps) / speed if speed else None

    def left_s(self, states: list[Progress]) -> list[float | None]:
        """The estimate, in seconds, of every point of ``states`` (``status()``'s) still to train: partial or
        missing (an unrecorded run has finished and needs only its record)."""
        pace = Pace.read(self.records)
        return [self.estimate_s(s, pace) for s in states if s.state in ("partial", "missing")]

    # ---------------------------------------------------------------------------------- running
    def dry_run(
        self, hours: float, fill: bool = False, finish_first: bool = False, finish_only: bool = False
    ) -> list[str]:
        """The commands ``run`` would start, in order, with their estimated length; nothing is run."""
        to_record, launches = self.plan()
        pace = Pace.read(self.records)
        lines = [f"record {s.point.run_dir(self.outputs)}" for s in to_record]
        # The same rule as `run`, simulated: a run starts when a job slot frees, and only if its estimate
        # ends before the deadline (a run without an estimate always starts); with `fill`, if the slot
        # frees FILL_FLOOR_S or more before the deadline, and what is not done by then is stopped.
        deadline = hours * 3600
        slots = [0.0] * self.jobs
        estimates = [self.estimate_s(state, pace) for state, _ in launches]
        queue = list(zip(launches, estimates, strict=True))
        while queue:
            slot = min(range(self.jobs), key=slots.__getitem__)
            index = _next_run(queue, deadline - slots[slot], finish_first or finish_only)
            (state, command), estimate = queue.pop(index)
            refusal = self._start_refusal(state, estimate, deadline - slots[slot], fill, finish_only)
            if refusal is not None:
                lines.append(refusal)
                continue
            what = "resume" if state.state == "partial" else "start"
            line = f"{what} {state.point.id} (at {state.env_steps} env steps, estimated {_hours(estimate)}"
            if fill and (estimate is None or slots[slot] + estimate > deadline):
                line += ", stopped at the deadline"
                slots[slot] = deadline
            else:
                slots[slot] += estimate or 0.0
            lines.append(f"{line}): {shlex.join(command)}")
        rule = "runs going then are stopped and resume next time" if fill else "no new start"
        order = ", those that can end in time first" if finish_first else ""
        order = ", only those that can end in time (and partial ones)" if finish_only else order
        lines.append(left_line(estimates, self.jobs))
        lines.append(f"{len(launches)} runs, {self.jobs} at a time{order}, {rule} after {hours:g} h")
        return lines

    def _start_refusal(
        self, state: Progress, estimate: float | None, left: float, fill: bool, finish_only: bool = False
    ) -> str | None:
        """Why a run must not start with ``left`` seconds to the deadline, or None."""
        if fill and left < FILL_FLOOR_S:
            return (
                f"not started: {state.point.id}: {_hours(max(0.0, left))} left, under the "
                f"{_hours(FILL_FLOOR_S)} a start needs (--fill)"
            )
        if finish_only and state.state != "partial" and (estimate is None or estimate > left):
            needs = "has no estimate" if estimate is None else f"needs about {_hours(estimate)}"
            return f"not started: {state.point.id} {needs}, {_hours(max(0.0, left))} left (--finish-only)"
        if not fill and estimate is not None and estimate > left:
            return (
                f"not started: {state.point.id} needs about {_hours(estimate)}, {_hours(max(0.0, left))} left"
            )
        return None

    def run(
        self, hours: float, fill: bool = False, finish_first: bool = False, finish_only: bool = False
    ) -> int:
        """Run the plan within ``hours`` (with ``fill``: stop what still runs then); returns 0 when every
        run it started ended well or was stopped at the deadline and the rest were left for lack of time,
        1 when a point was refused (its run directory in use by a live run, or not the campaign's) or a
        run failed, 128 + the signal that stopped it. One campaign at a time per outputs folder (a second
        one would start the same points), and one runner per point whatever the outputs (claim_point)."""
        self.outputs.mkdir(parents=True, exist_ok=True)
        with open(self.outputs / ".campaign.lock", "a+") as lock:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                lock.seek(0)
                raise CampaignBusy(
                    f"another mcrs-campaign run uses {self.outputs} (pid {lock.read().strip() or '?'})"
                ) from None
            lock.seek(0)
            lock.truncate()
            lock.write(str(os.getpid()))
            lock.flush()
            return self._run(hours, fill, finish_first, finish_only)

    def _run(self, hours: float, fill: bool, finish_first: bool, finish_only: bool) -> int:
        deadline = self.deadline = time.time() + hours * 3600
        to_record, launches = self.plan()
        for state in to_record:
            self._record(state.point)
        pace = Pace.read(self.records)
        here = MachinePace()
        queue = list(launches)
        running: list[Job] = []
        not_started = refused = stopped_at_deadline = 0
        previous = {sig: signal.signal(sig, self._on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
        try:
            while (queue or running) and self.stop_signal is None:
                if fill and time.time() >= deadline:
                    _print(f"campaign: the {hours:g} h are over: stopping {len(running)} runs (--fill)")
                    stopped_at_deadline = len(running)
                    self._stop(running)
                    running = []
                    not_started += len(queue)
                    break
                while queue and len(running) < self.jobs and self.stop_signal is None:
                    recorded = [self.estimate_s(state, pace) for state, _ in queue]
                    estimates = [  # a partial run's estimate is its own speed here already
                        e if state.state == "partial" else here.scale(e, (state.point.env, state.point.algo))
                        for (state, _), e in zip(queue, recorded, strict=True)
                    ]
                    index = _next_run(
                        list(zip(queue, estimates, strict=True)),
                        deadline - time.time(),
                        finish_first or finish_only,
                    )
                    (state, command), estimate = queue.pop(index), estimates[index]
                    refusal = self._start_refusal(state, estimate, deadline - time.time(), fill, finish_only)
                    if refusal is not None:
                        _print(refusal)
                        not_started += 1
                        continue
                    job = self._launch(state, command)
                    if job is None:
                        refused += 1
                    else:
                        job.estimate_s = recorded[index] if state.state == "missing" else None
                        running.append(job)
                time.sleep(1.0)
                for job in [j for j in running if j.process.poll() is not None]:
                    running.remove(job)
                    self._finish(job)
                    pace = Pace.read(self.records)
                    if job.process.returncode == 0 and job.estimate_s:
                        kind = (job.point.env, job.point.algo)
                        here.observe(kind, job.estimate_s, time.time() - job.started)
                        _print(
                            f"campaign: runs here take {here.factor():.2f}x the recorded pace, {' '.join(kind)} "
                            f"{here.factor(kind):.2f}x (the next starts' estimates are scaled by their own map "
                            "and algorithm's, else by all)"
                        )
            if self.stop_signal is not None:
                self._stop(running)
                return 128 + self.stop_signal
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        ended = len(launches) - not_started - refused - stopped_at_deadline
        stopped = f", {stopped_at_deadline} stopped at the deadline (resumable)" if fill else ""
        _print(f"campaign: {ended} runs ended{stopped}, {not_started} not started (time budget)")
        if refused:
            _print(
                f"campaign: {refused} runs not started: another campaign trains them, or their directories "
                "are in use or not the campaign's (exit status 1)"
            )
        if self.failed:
            _print(f"campaign: {self.failed} runs failed (exit status 1)")
        return 1 if refused or self.failed else 0

    def _on_signal(self, signum: int, frame: object) -> None:
        if self.stop_signal is None:
            _print(f"campaign: {signal.Signals(signum).name}: stopping the running children")
        self.stop_signal = signum

    def _refusal(self, point: Point, state: str) -> str | None:
        """Why the campaign must not touch ``point``'s run directory now, or None. A run whose lock is
        held (a user's mcrs-train, or another tool) is left alone, and a directory the campaign did not
        start (no campaign.log) is never moved aside: only its owner knows what it holds."""
        run_dir = point.run_dir(self.outputs)
        holder = lock_holder(run_dir)
        if holder is not None:
            return (
                f"{point.id}: its run directory {run_dir} is in use by {holder}: the campaign leaves a "
                "live run alone; run the campaign again once it has ended"
            )
        if state == "missing" and run_dir.exists() and not (run_dir / LOG).is_file():
            return (
                f"{point.id}: {run_dir} holds a run that mcrs-campaign did not start (no {LOG}): move it "
                "away or resume it yourself (mcrs-train resume=); the campaign does not touch it"
            )
        return None

    def _launch(self, state: Progress, command: list[str]) -> Job | None:
        run_dir = state.point.run_dir(self.outputs)
        refusal = self._refusal(state.point, state.state)  # first: a refused point leaves no trace
        if refusal is not None:
            _print(f"not started: {refusal}")
            return None
        claim = claim_point(self.records, state.point, self.outputs)
        if isinstance(claim, str):
            _print(
                f"not started: {state.point.id}: another mcrs-campaign run trains it ({claim}; "
                f"{claim_path(self.records, state.point)}); its record lands in {self.records} when it ends"
            )
            return None
        if progress(state.point, self.outputs, self.records, self.total).state == "done":
            claim.close()  # another runner finished and recorded it since this one's plan was made
            _print(f"not started: {state.point.id}: done meanwhile (its record in {self.records})")
            return None
        if state.state == "missing" and run_dir.exists():  # a start that died before its first checkpoint
            aside = run_dir.with_name(f"{run_dir.name}.failed-{time.strftime('%Y%m%d-%H%M%S')}")
            run_dir.rename(aside)
            _print(f"moved {run_dir} (no checkpoint) to {aside}")
        run_dir.mkdir(parents=True, exist_ok=True)
        log = open(run_dir / LOG, "a")  # noqa: SIM115 (closed when the child ends)
        log.write(f"\n$ {shlex.join(command)}\n")
        log.flush()
        env = {**os.environ, "OMP_NUM_THREADS": str(self.threads), "HYDRA_FULL_ERROR": "0"}
        process = subprocess.Popen(
            command,
            stdout=log,
            stderr=subprocess.STDOUT,
            env=env,
            start_new_session=True,
            pass_fds=(claim.fileno(),),
        )
        what = "resumed" if state.state == "partial" else "started"
        _print(f"{what} {state.point.id} (pid {process.pid}): {shlex.join(command)}")
        return Job(state.point, command, process, log, claim)

    def _finish(self, job: Job, stopped: bool = False) -> None:
        job.log.close()
        run_dir = job.point.run_dir(self.outputs)
        session = {
            "started": time.strftime("%Y-%m-%dT%H:%M:%S%z", time.localtime(job.started)),
            "ended": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "wall_s": round(time.time() - job.started, 1),
            "command": ["python", *job.command[1:]],  # the interpreter's path says nothing elsewhere
            "returncode": job.process.returncode,
            "stopped_by_campaign": stopped,
            "git": git_facts(),
            "machine": job.machine,
            "load_avg_end": [round(x, 2) for x in os.getloadavg()],
        }
        with open(run_dir / SESSIONS, "a") as f:
            f.write(json.dumps(session) + "\n")
        if job.process.returncode != 0 and not stopped:
            self.failed += 1
            tail = (run_dir / LOG).read_text().strip().splitlines()[-5:]
            _print(
                f"failed: {job.point.id} (exit {job.process.returncode}); {run_dir / LOG} ends:\n  "
                + "\n  ".join(tail)
            )
        self._record(job.point)
        job.claim.close()  # ended and recorded: the point is free again

    def _record(self, point: Point) -> None:
        run_dir = point.run_dir(self.outputs)
        holder = lock_holder(run_dir)
        if holder is not None:  # a live run: its checkpoint may change under the record (and the pruning)
            _print(f"not recorded: {point.id}: {run_dir} is in use by {holder}")
            return
        try:
            path, record = make_record(run_dir, self.records)
            outcome = write_record(path, record)
        except (RecordError, ckpt.CheckpointError) as error:
            _print(f"not recorded: {point.id}: {error}")
            return
        _print(f"{outcome} {path} ({record['status']} at {record['checkpoint_env_steps']} env steps)")
        if record["status"] != "finished":
            return
        for line in figure9.before_prune(self.tsne, point, self.outputs, self.records):
            _print(line)
        if self.prune:
            before, after = ckpt.prune_bulk(run_dir)
            if after < before:
                _print(
                    f"pruned {ckpt.checkpoint_path(run_dir)}: {before / 1e6:.0f} MB -> {after / 1e6:.0f} MB"
                )
        if self.evaluations and self.stop_signal is None:
            run_pending(
                plan(self.evaluations, [point], self.records, self.outputs)[0], self.outputs, self.records
            )
        if figure9.missing(self.tsne, self.records) and self.make_tsne and self.stop_signal is None:
            if self.deadline - time.time() < TSNE_FLOOR_S:
                _print(
                    f"tsne: not now ({_hours(TSNE_FLOOR_S)} needed before the deadline); a later run makes it"
                )
                return
            for line in figure9.pending(self.tsne, self.outputs, self.records):
                _print(line)

    def _stop(self, running: list[Job]) -> None:
        for job in running:
            with contextlib.suppress(ProcessLookupError):  # already gone
                os.killpg(job.process.pid, signal.SIGINT)
        end = time.time() + STOP_GRACE_S
        for job in running:
            try:
                job.process.wait(timeout=max(0.0, end - time.time()))
            except subprocess.TimeoutExpired:
                os.killpg(job.process.pid, signal.SIGKILL)
                job.process.wait()
            self._finish(job, stopped=True)
