"""The handler and formatter of the commands' text log (``conf/hydra/job_logging/mcrs.yaml``).

Apart from :mod:`mcrs.experiment.run.logging` (TorchRL's loggers) because Hydra builds them before the command
runs: importing them must not load torch, so that a refused command is refused at once.
"""

from __future__ import annotations

import logging
import re

ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")  # colour and cursor codes


class PlainFormatter(logging.Formatter):
    """A formatter whose output has no ANSI colour codes (a log file is read in an editor)."""

    def format(self, record: logging.LogRecord) -> str:
        return ANSI.sub("", super().format(record))


class TqdmHandler(logging.StreamHandler):
    """Writes each record with ``tqdm.write``, which lifts the progress bar, prints and redraws it.

    A record logged with ``extra={"console": False}`` (a message the command prints itself) is skipped.
    """

    def emit(self, record: logging.LogRecord) -> None:
        if getattr(record, "console", True) is False:
            return
        try:
            from tqdm import tqdm

            tqdm.write(self.format(record), file=self.stream)
            self.flush()
        except Exception:  # logging's contract: report the failure, never raise
            self.handleError(record)
