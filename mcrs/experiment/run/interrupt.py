"""Stopping a run cleanly on Ctrl-C (SIGINT) or SIGTERM.

The signal only asks for a stop: the loop finishes its collector batch, writes a checkpoint there so a resume
continues exactly, and raises :class:`RunInterrupted`. ``mcrs-train`` then exits with 128 + the signal. A
second signal during the save is ignored.
"""

from __future__ import annotations

import signal
import threading
from pathlib import Path
from types import FrameType, TracebackType

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class RunInterrupted(KeyboardInterrupt):
    """A run stopped by a signal after its checkpoint; a ``KeyboardInterrupt`` so that code that stops on
    Ctrl-C still stops."""

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
    """SIGTERM outside the training loop, raised where Ctrl-C's ``KeyboardInterrupt`` would be."""

    signal_name = "SIGTERM"
    exit_code = 128 + signal.SIGTERM


def _raise_terminated(signum: int, frame: FrameType | None) -> None:
    raise Terminated()


class TerminateAsInterrupt:
    """A context in which SIGTERM raises :class:`Terminated`; does nothing outside the main thread."""

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
    """A context in which SIGINT and SIGTERM set :attr:`signum` instead of stopping; does nothing outside the
    main thread."""

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
