"""Stopping a run cleanly on Ctrl-C (SIGINT) or SIGTERM: the signal only asks for a stop; the training loop
finishes the collector batch it is in, writes a checkpoint at that consistent point (counters, replay, random
state: a resume continues exactly) and raises :class:`RunInterrupted`, which ``mcrs-train`` turns into one
line, the resume command and exit status 128 + the signal (130, 143).

A second signal while the checkpoint is written is noted and ignored, so it cannot cut the save short (the
writes are atomic anyway: an interrupted write leaves the previous checkpoint as it was).
"""

from __future__ import annotations

import signal
import threading
from pathlib import Path
from types import FrameType, TracebackType

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class RunInterrupted(KeyboardInterrupt):
    """A run stopped by a signal after writing its checkpoint.

    A ``KeyboardInterrupt``, so that code that stops on Ctrl-C (a notebook, a script's ``except
    KeyboardInterrupt``) still stops; ``exit_code`` is the shell's 128 + signal number.
    """

    def __init__(self, signum: int, run_dir: Path, env_steps: int, checkpoint: Path) -> None:
        self.signum, self.run_dir, self.env_steps, self.checkpoint = signum, run_dir, env_steps, checkpoint
        super().__init__(
            f"{self.signal_name}: stopped at env step {env_steps}; checkpoint {checkpoint}; "
            f"resume with: mcrs-train resume={run_dir}"
        )

    @property
    def signal_name(self) -> str:
        return signal.Signals(self.signum).name

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


class Terminated(KeyboardInterrupt):
    """SIGTERM outside the training loop (while the run is built, or while its report is written), raised
    where Ctrl-C's ``KeyboardInterrupt`` would be, so both stop the same way; ``exit_code`` is 143."""

    signal_name = "SIGTERM"
    exit_code = 128 + signal.SIGTERM


def _raise_terminated(signum: int, frame: FrameType | None) -> None:
    raise Terminated()


class TerminateAsInterrupt:
    """While active (a context manager), SIGTERM raises :class:`Terminated` instead of killing the process
    without a word; :class:`StopSignals` takes over inside the training loop. Outside the main thread it
    does nothing."""

    def __init__(self) -> None:
        self._previous: object | None = None

    def __enter__(self) -> TerminateAsInterrupt:
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGTERM, _raise_terminated)
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGTERM, self._previous)  # type: ignore[arg-type]
            self._previous = None


class StopSignals:
    """While active (a context manager), SIGINT and SIGTERM set :attr:`signum` instead of stopping the
    process; the previous handlers come back on exit. Outside the main thread (where Python cannot
    install handlers) it does nothing and the signals keep their usual effect."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self._previous: dict[int, object] = {}

    @property
    def requested(self) -> bool:
        return self.signum is not None

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.signum is None:
            self.signum = signum  # the first one decides the exit status; later ones are ignored

    def __enter__(self) -> StopSignals:
        if threading.current_thread() is threading.main_thread():
            for sig in STOP_SIGNALS:
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)  # type: ignore[arg-type]
        self._previous.clear()
