"""The trainer's collector: one process (``train.collector=single``) or several (``multiprocess``).

``multiprocess`` runs TorchRL's ``MultiSyncCollector`` over ``train.collector_workers`` spawned processes,
each with ``num_envs / workers`` environments, and concatenates their batches so the trainer still receives
``[num_envs, T]`` whole episodes. Batch ``k`` seeds worker 0 with ``batch_seed(seed, k)`` and the others with
the seeds TorchRL chains from it, so a multiprocess run is reproducible and resumes exactly, though its
episodes differ from a single-process run's.

TorchRL reports only a failed worker's exit code, so each worker writes its traceback to a temporary folder
for :class:`CollectorWorkerFailed`. A worker killed from outside leaves none, and TorchRL waits for some
replies without a timeout, so :class:`WorkerWatch` wakes the main thread when a worker has died.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import tempfile
import threading
import traceback
from collections.abc import Iterator
from pathlib import Path

import torch
from tensordict import TensorDictBase
from torchrl.collectors import BaseCollector, Collector, MultiSyncCollector
from torchrl.envs import EnvBase, TransformedEnv

from mcrs.env.config import EnvConfig
from mcrs.experiment.training.task import Task, as_task, with_agent_state


@contextlib.contextmanager
def _workers_ignore_sigint() -> Iterator[None]:
    """Start worker processes with SIGINT ignored, since Ctrl-C reaches the whole process group and the
    trainer decides how to stop."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


class CollectorWorkerFailed(RuntimeError):
    """A collector worker raised or died; the message carries its exception, or its pid and how it ended."""


class _WorkerDied(BaseException):
    """Raised in the main thread by the watch's wake-up signal; not an ``Exception``, which TorchRL's wait
    would catch and only log."""


def describe_exit(pid: int, exitcode: int) -> str:
    """``a collector worker (pid 7438) died (signal 9, SIGKILL)`` or ``... exited with status 1``."""
    if exitcode < 0:
        try:
            name = f", {signal.Signals(-exitcode).name}"
        except ValueError:
            name = ""
        return f"a collector worker (pid {pid}) died (signal {-exitcode}{name})"
    return f"a collector worker (pid {pid}) exited with status {exitcode}"


class WorkerWatch:
    """Tells when a worker process has ended, and then ends a wait on the workers (:meth:`waiting`). A daemon
    thread polls the workers' exit codes during a wait and sends SIGUSR1 to the main thread, whose handler
    raises there; outside the main thread only the checks before and after a wait remain."""

    WAKE = signal.SIGUSR1

    def __init__(self, procs: list, interval: float = 0.5) -> None:
        self.procs = list(procs)
        self.pids = [int(p.pid) for p in self.procs]
        self.interval = interval
        self.dead: tuple[int, int] | None = None
        self._waiting = threading.Event()
        self._closed = threading.Event()
        self._previous: object | None = None
        self._thread: threading.Thread | None = None
        if threading.current_thread() is threading.main_thread():
            self._main = threading.get_ident()
            self._previous = signal.signal(self.WAKE, self._wake)
            self._thread = threading.Thread(target=self._watch, name="mcrs-worker-watch", daemon=True)
            self._thread.start()

    def check(self) -> tuple[int, int] | None:
        """``(pid, exit code)`` of a worker that has ended, or None; TorchRL terminates the others once one
        dies, so one that ended otherwise is named."""
        if self.dead is not None:
            return self.dead
        ended = []
        for pid, proc in zip(self.pids, self.procs, strict=True):
            try:
                code = proc.exitcode
            except (ValueError, OSError):  # closed by TorchRL after terminating it: not the first to die
                continue
            if code is not None:
                ended.append((pid, int(code)))
        if ended:
            first = [e for e in ended if e[1] != -signal.SIGTERM] or ended
            self.dead = first[0]
        return self.dead

    def failure(self) -> CollectorWorkerFailed:
        pid, code = self.dead or (0, 0)
        return CollectorWorkerFailed(describe_exit(pid, code))

    @contextlib.contextmanager
    def waiting(self) -> Iterator[None]:
        """Wait on the workers; a worker that has ended, or an error that comes with a dead worker, raises
        :class:`CollectorWorkerFailed`."""
        if self.check() is not None:
            raise self.failure()
        self._waiting.set()
        try:
            yield
        except _WorkerDied:
            raise self.failure() from None
        except CollectorWorkerFailed:
            raise
        except Exception as error:
            if self.check() is None:
                raise
            raise self.failure() from error
        finally:
            self._waiting.clear()

    def _wake(self, signum: int, frame: object) -> None:
        if self._waiting.is_set() and self.dead is not None:
            self._waiting.clear()
            raise _WorkerDied()

    def _watch(self) -> None:
        while not self._closed.is_set():
            if not self._waiting.wait(timeout=self.interval):
                continue  # the trainer is not waiting on the workers
            if self._closed.wait(self.interval):
                return
            if self._waiting.is_set() and self.check() is not None:
                signal.pthread_kill(self._main, self.WAKE)
                return  # once: the wait ends, and every later one fails at its first check

    def close(self) -> None:
        """Stop the thread and put the previous SIGUSR1 handler back."""
        self._closed.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        if self._previous is not None and threading.current_thread() is threading.main_thread():
            signal.signal(self.WAKE, self._previous)  # type: ignore[arg-type]
            self._previous = None


class _WorkerEnv:
    """Mixed into the task's env in a collector worker: records a failure's traceback and seeds the worker's
    exploration with the env."""

    _error_dir: str

    def _record(self) -> None:
        path = Path(self._error_dir) / f"worker_{os.getpid()}.txt"
        path.write_text(traceback.format_exc())

    def _set_seed(self, seed: int | None) -> None:
        super()._set_seed(seed)
        torch.manual_seed(0 if seed is None else seed)  # the worker's exploration draws

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        try:
            return super()._reset(tensordict, **kwargs)
        except BaseException:
            self._record()
            raise

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        try:
            return super()._step(tensordict)
        except BaseException:
            self._record()
            raise


def _in_worker(env: EnvBase, error_dir: str) -> EnvBase:
    """``env`` with :class:`_WorkerEnv` mixed into its base env."""
    base = env.base_env if isinstance(env, TransformedEnv) else env
    base.__class__ = type(f"_Worker{type(base).__name__}", (_WorkerEnv, type(base)), {})
    base._error_dir = error_dir
    return env


class WorkerEnvFactory:
    """Builds one worker's environments in the worker process; picklable, like the task."""

    def __init__(
        self, task: Task | EnvConfig, num_envs: int, hidden_dim: int, error_dir: str, device: torch.device
    ) -> None:
        self.task, self.num_envs, self.hidden_dim = as_task(task), num_envs, hidden_dim
        self.error_dir, self.device = error_dir, device

    def __call__(self) -> EnvBase:
        env = _in_worker(self.task.make_env(self.num_envs, self.device), self.error_dir)
        return with_agent_state(env, self.task, self.num_envs, self.hidden_dim, self.device)


class TrainingCollector:
    """The collector of a run, with the calls the trainer makes, whichever kind it is."""

    def __init__(
        self,
        kind: str,
        env: EnvBase,
        policy: torch.nn.Module,
        task: Task | EnvConfig,
        hidden_dim: int,
        workers: int,
        device: torch.device,
        num_envs: int | None = None,
    ) -> None:
        self.kind, self.env = kind, env
        if num_envs is None:  # an EnvConfig carries it; a Task does not
            if not isinstance(task, EnvConfig):
                raise TypeError("TrainingCollector(task=...) needs num_envs")
            num_envs = task.num_envs
        task = as_task(task)
        T = task.max_steps
        self.error_dir: str | None = None
        self.watch: WorkerWatch | None = None
        if kind == "single":
            self.collector: BaseCollector = Collector(
                env,
                policy,
                frames_per_batch=num_envs * T,  # whole episodes: every batch row is one episode
                total_frames=-1,
                device=device,
                trust_policy=True,
                auto_register_policy_transforms=False,
            )
            return
        per_worker = num_envs // workers
        self.error_dir = tempfile.mkdtemp(prefix="mcrs-collector-")
        with _workers_ignore_sigint():
            self.collector = MultiSyncCollector(
                [
                    WorkerEnvFactory(task, per_worker, hidden_dim, self.error_dir, device)
                    for _ in range(workers)
                ],
                policy,
                frames_per_batch=num_envs * T,  # split evenly: per_worker whole episodes each
                total_frames=-1,
                device=device,
                cat_results=0,  # [workers * per_worker, T]: the single-process layout
                trust_policy=True,
                auto_register_policy_transforms=False,
            )
        self.watch = WorkerWatch(self.collector.procs)

    def _waiting(self) -> contextlib.AbstractContextManager:
        return self.watch.waiting() if self.watch is not None else contextlib.nullcontext()

    def __iter__(self) -> Iterator[TensorDictBase]:
        return iter(self.collector)

    def start_batch(self, seed: int) -> None:
        """Seed and reset the environments, so the next batch starts fresh episodes from ``seed``."""
        if self.kind == "single":
            self.env.set_seed(seed)
            self.collector.reset()
            return
        with self._waiting():
            self.collector.set_seed(seed)
            self.collector.reset()

    def sync_weights(self) -> None:
        """Send the learner's weights and epsilon to the workers; one process shares the objects."""
        if self.kind != "single":
            with self._waiting():
                self.collector.update_policy_weights_()

    def next_batch(self, iterator: Iterator[TensorDictBase]) -> TensorDictBase:
        try:
            with self._waiting():
                return next(iterator)
        except Exception as error:
            cause = self.worker_error()
            if cause is None:
                raise
            raise CollectorWorkerFailed(f"a collector worker failed: {cause}") from error

    def worker_error(self) -> str | None:
        """The last line of a failed worker's recorded traceback, if any."""
        if self.error_dir is None:
            return None
        for path in sorted(Path(self.error_dir).glob("worker_*.txt")):
            lines = [line for line in path.read_text().splitlines() if line.strip()]
            if lines:
                return lines[-1].strip()
        return None

    def shutdown(self) -> None:
        """Stop the workers without masking the exception that stopped the run."""
        try:
            if self.watch is not None:
                self.watch.close()
            self.collector.shutdown()
        except Exception:  # a worker already dead: its error is the one that matters
            pass
        finally:
            if self.error_dir is not None:
                shutil.rmtree(self.error_dir, ignore_errors=True)
