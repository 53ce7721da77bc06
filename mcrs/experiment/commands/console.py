"""The handler and formatter of the commands' text log (``conf/hydra/job_logging/mcrs.yaml``).

Hydra builds them before the command runs, so this module must not load torch or tqdm: a refused command is
refused at once.
"""

from __future__ import annotations

import logging
import re

ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")  # colour and cursor codes


class PlainFormatter(logging.Formatter):
    """A formatter without ANSI colour codes, since a log file is read in an editor."""

    def format(self, record: logging.LogRecord) -> str:
        return ANSI.sub("", super().format(record))


class TqdmHandler(logging.StreamHandler):
    """Writes each record with ``tqdm.write``, which lifts the progress bar; a record with ``extra={"console":
    False}`` is skipped."""

    def emit(self, record: logging.LogRecord) -> None:
        if getattr(record, "console", True) is False:
            return
        try:
            from tqdm import tqdm

            tqdm.write(self.format(record), file=self.stream)
            self.flush()
        except Exception:  # logging's contract: report the failure, never raise
            self.handleError(record)
