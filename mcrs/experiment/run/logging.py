"""Metric logging through TorchRL's loggers with grouped names (``train/``, ``eval/``, ``time/``), and the
run's text log.

``csv`` writes ``<run>/logs/scalars/<group>/<name>.csv``, ``tensorboard`` writes ``<run>/logs/``, and
``wandb`` runs offline into ``<run>/wandb/`` with the same CSV files beside it, which ``mcrs-report`` and a
resume read. Videos are GIFs encoded with Pillow in ``<run>/videos/``, also sent to TensorBoard and wandb;
TorchRL's ``log_video`` would need moviepy. The text log is the ``mcrs.run`` logger (:func:`log_event`), which
``conf/hydra/job_logging/mcrs.yaml`` writes to ``<run>/train.log``.
"""

from __future__ import annotations

import contextlib
import csv
import logging
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import OmegaConf
from torchrl.record.loggers import CSVLogger, Logger, TensorboardLogger, WandbLogger
from tqdm.auto import tqdm

from mcrs.choices import LOGGER_BACKENDS, WANDB_MODES


def make_logger(
    backend: str, run_dir: Path, config: dict[str, Any], project: str = "mcrs", mode: str = "offline"
) -> Logger:
    """A TorchRL logger for the run, with the resolved config logged as hyper-parameters."""
    quiet_torchrl()
    name = run_dir.name
    if backend == "csv":
        logger = CSVLogger(exp_name="logs", log_dir=str(run_dir))
    elif backend == "tensorboard":
        logger = TensorboardLogger(exp_name="logs", log_dir=str(run_dir))
    elif backend == "wandb":
        if mode not in WANDB_MODES:
            raise ValueError(f"logger.wandb_mode={mode!r}: allowed values are {', '.join(WANDB_MODES)}")
        os.environ.setdefault("WANDB_SILENT", "true")
        return WandbLoggerWithHistory(
            run_dir,
            exp_name=name,
            save_dir=str(run_dir),
            project=project,
            offline=mode == "offline",
            config=config,
        )
    else:
        raise ValueError(f"logger.backend={backend!r}: allowed values are {', '.join(LOGGER_BACKENDS)}")
    logger.log_hparams(_hparams(config))
    return logger


class WandbLoggerWithHistory(WandbLogger):
    """TorchRL's ``WandbLogger`` that also keeps every scalar in ``<run>/logs/scalars/``, since wandb's
    ``.wandb`` file has no public reader."""

    def __init__(self, run_dir: Path, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.history = CSVLogger(exp_name="logs", log_dir=str(run_dir))

    def log_scalar(self, name: str, value: Any, step: int | None = None, **options: Any) -> None:
        super().log_scalar(name, value, step=step, **options)
        if isinstance(value, (int, float)):  # not a wandb.Video (log_video)
            self.history.log_scalar(name, float(value), step=step)


def flatten_config(config: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"algo.memory.delta": 0.0013}``: nested dicts become dotted names."""
    out: dict[str, Any] = {}
    for key, value in config.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten_config(value, f"{name}."))
        else:
            out[name] = value
    return out


def _hparams(config: dict[str, Any]) -> dict[str, Any]:
    return {
        k: v if isinstance(v, (int, float, str, bool)) else str(v) for k, v in flatten_config(config).items()
    }


#: What a run did, at INFO (the trainer's evaluations and checkpoints): mcrs-train writes it to train.log.
RUN_LOG = logging.getLogger("mcrs.run")


def log_event(message: str) -> None:
    """One line of the run's text log (:data:`RUN_LOG`)."""
    RUN_LOG.info("%s", message)


def metrics_line(metrics: dict[str, float]) -> str:
    """``"episode_reward 11.04, uncertainty 76.26"``: an evaluation's means for the text log."""
    return ", ".join(f"{k} {v:.4g}" for k, v in metrics.items() if not k.endswith("_std"))


def log_scalars(logger: Logger, values: dict[str, float], step: int) -> None:
    for name, value in values.items():
        logger.log_scalar(name, float(value), step=step)


def close_log_files(logger: Logger) -> None:
    """Close the CSV logger's files now; TorchRL closes them at collection, where a failed flush would print
    after the run's one-line error."""
    files = getattr(getattr(logger, "experiment", None), "files", None)
    if not isinstance(files, dict):
        return
    for handle in list(files.values()):
        with contextlib.suppress(OSError):  # the flush failed; the file is closed all the same
            handle.close()
    files.clear()


def log_video(
    logger: Logger, run_dir: Path, name: str, frames: list[np.ndarray], step: int, fps: int = 5
) -> Path:
    """Log ``frames`` (``[H, W, 3]`` uint8) as the GIF ``name`` at ``step``, in ``<run>/videos/`` and
    TensorBoard's or wandb's log."""
    from mcrs.env.render import encode_gif  # matplotlib and Pillow: only for videos

    gif = encode_gif(frames, fps)
    path = run_dir / "videos" / f"{name.replace('/', '_')}_{step}.gif"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(gif)
    if isinstance(logger, TensorboardLogger):
        from torch.utils.tensorboard.summary import Summary

        height, width, channels = frames[0].shape
        image = Summary.Image(height=height, width=width, colorspace=channels, encoded_image_string=gif)
        summary = Summary(value=[Summary.Value(tag=name, image=image)])
        logger.experiment._get_file_writer().add_summary(summary, step)  # what SummaryWriter.add_video does
        logger.experiment.flush()
    elif isinstance(logger, WandbLogger):
        import wandb

        # TorchRL's per-group step bookkeeping, as for the scalars (the value is not a float here).
        logger.log_scalar(name, wandb.Video(str(path), format="gif"), step=step)
    return path


#: Seconds between two lines of :class:`PlainProgress` (a log file, not a terminal).
PLAIN_INTERVAL_S = 60.0


def progress_bar(
    total: int,
    initial: int,
    enabled: bool,
    description: str,
    unit: str = "step",
    plain: bool | None = None,
    interval: float = PLAIN_INTERVAL_S,
):
    """Progress over ``total`` units: a tqdm bar on a terminal, else a :class:`PlainProgress` line every
    ``interval`` seconds. ``plain`` defaults to True when stderr is no terminal or parallel sweep jobs share
    it."""
    if plain is None:
        plain = not _is_terminal(sys.stderr) or parallel_sweep_job()
    if enabled and plain:
        return PlainProgress(total, initial, description, unit, interval)
    return tqdm(
        total=total,
        initial=initial,
        unit=unit,
        unit_scale=True,
        dynamic_ncols=True,
        mininterval=1.0,
        disable=not enabled,
        desc=description,
    )


class PlainProgress:
    """The progress bar as plain lines on stderr, for a console that is no terminal::

        qmix map20: 120k/2M steps (6%), 1.92k steps/s, elapsed 0:01:03, ETA 0:16:29, eps=0.050, eval_reward=12.3

    One line at the start, at most one every ``interval`` seconds, and one at the close."""

    def __init__(self, total: int, initial: int, description: str, unit: str = "step",
                 interval: float = PLAIN_INTERVAL_S) -> None:  # fmt: skip
        self.total, self.n, self.initial = int(total), int(initial), int(initial)
        self.description, self.unit, self.interval = description, unit, float(interval)
        self.postfix: dict[str, Any] = {}
        self.start = self.last = time.monotonic()
        self.closed = False
        self._write()

    def update(self, n: int = 1) -> None:
        self.n += int(n)
        if time.monotonic() - self.last >= self.interval:
            self._write()

    def set_postfix(
        self, ordered_dict: dict[str, Any] | None = None, refresh: bool = True, **kwargs: Any
    ) -> None:
        self.postfix = {**(ordered_dict or {}), **kwargs}

    def set_description(self, description: str, refresh: bool = True) -> None:
        self.description = description

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self._write()

    def __enter__(self) -> PlainProgress:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def line(self) -> str:
        """The current line, without the newline."""
        elapsed = time.monotonic() - self.start
        rate = (self.n - self.initial) / elapsed if elapsed > 0 else 0.0

        size = _scaled
        parts = [f"{size(self.n)}/{size(self.total)} {self.unit}s"]
        if self.total > 0:
            parts[0] += f" ({100 * self.n / self.total:.0f}%)"
        if rate > 0:
            parts.append(f"{size(rate)} {self.unit}s/s")
        parts.append(f"elapsed {tqdm.format_interval(elapsed)}")
        if rate > 0 and self.n < self.total:
            parts.append(f"ETA {tqdm.format_interval((self.total - self.n) / rate)}")
        parts += [f"{k}={v}" for k, v in self.postfix.items()]
        return f"{self.description}: {', '.join(parts)}"

    def _write(self) -> None:
        self.last = time.monotonic()
        print(self.line(), file=sys.stderr, flush=True)


def _scaled(x: float) -> str:
    """``2M``, ``120k``, ``1.92k``, ``14.2``: three significant digits and a k/M/G suffix."""
    for scale, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(x) >= scale:
            return f"{x / scale:.3g}{suffix}"
    return f"{x:.3g}"


def _is_terminal(stream: Any) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # replaced by an object without it, or closed
        return False


def parallel_sweep_job() -> bool:
    """Whether a sweep launcher (joblib, Ray, Slurm) runs this job beside others, whose bars would overwrite
    each other."""
    from hydra.core.hydra_config import HydraConfig  # Hydra only matters under a command
    from hydra.types import RunMode

    if not HydraConfig.initialized():
        return False
    hydra = HydraConfig.get()
    if hydra.mode != RunMode.MULTIRUN:
        return False
    launcher = str(OmegaConf.select(hydra, "launcher._target_", default="") or "")
    return not launcher.endswith("BasicLauncher")


def quiet_torchrl() -> None:
    """Turn TorchRL's INFO lines off, which would break the progress bar, unless ``RL_LOGGING_LEVEL`` is set."""
    if "RL_LOGGING_LEVEL" not in os.environ:
        logger = logging.getLogger("torchrl")
        logger.setLevel(max(logger.level, logging.WARNING))


class ScalarFileError(ValueError):
    """A CSV-logger file with a row that is not ``step,value`` numbers."""


def scalar_file(run_dir: Path, name: str) -> Path:
    """Where ``csv`` and ``wandb`` log the metric ``name`` (``eval/episode_reward``) of a run."""
    return run_dir / "logs" / "scalars" / f"{name}.csv"


def read_scalar_rows(path: Path) -> list[tuple[int, float]]:
    """The ``step,value`` rows of a CSV-logger file in the order written; a resumed run repeats steps."""
    out = []
    with open(path, newline="", errors="replace") as f:
        for line, row in enumerate(csv.reader(f), start=1):
            if len(row) != 2:
                continue
            try:
                step, value = float(row[0]), float(row[1])
            except ValueError:
                raise ScalarFileError(f"{path}:{line}: not a step,value row of numbers: {row!r}") from None
            if not (step >= 0 and math.isfinite(step)):
                raise ScalarFileError(f"{path}:{line}: step {row[0]!r} is not a whole number >= 0")
            out.append((int(step), value))
    return out


def sorted_points(rows: list[tuple[int, float]] | list[list[float]]) -> tuple[np.ndarray, np.ndarray]:
    """``(steps, values)`` sorted by step; a repeated step keeps the last value."""
    points = {int(step): float(value) for step, value in rows}
    steps = np.array(sorted(points), dtype=np.int64)
    return steps, np.array([points[s] for s in steps], dtype=np.float64)
