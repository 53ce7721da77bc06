"""Whole collector batches: the run's length and its evaluation interval, as the command line sets them.

A run collects ``train.num_envs`` whole episodes at a time, so a length or interval that is not a whole number
of batches would be rounded up silently (``train.total_env_steps=4000`` with batches of 1600 trains 4800
steps). A command line that sets one is refused, naming the nearest exact values.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any


def collector_batch(cfg: Any) -> int:
    """Env steps per collector batch: ``train.num_envs`` episodes of ``env.max_steps`` (or ``task.max_steps``;
    0 when a task node does not say)."""
    return int(cfg.train.num_envs) * _max_steps(cfg)[1]


def _max_steps(cfg: Any) -> tuple[str, int]:
    """Where the episode length comes from, and its value (0 when a task node does not say)."""
    task = getattr(cfg, "task", None)
    if task is None:
        return "env.max_steps", int(cfg.env.max_steps)
    steps = task.get("max_steps") if hasattr(task, "get") else None
    return "task.max_steps", steps if isinstance(steps, int) and not isinstance(steps, bool) else 0


#: Fields counted in env steps that whole collector batches must honour exactly when a command sets them.
BATCHED_FIELDS = ("train.total_env_steps", "train.eval_interval")


def whole_batch_errors(cfg: Any, explicit: Iterable[str]) -> list[str]:
    """The length or evaluation interval set on the command line (``explicit`` dotted keys) that is not a
    whole number of collector batches, naming the nearest values that are. A preset's values are not checked,
    so that runs recorded with them stay comparable; :func:`rounding_notes` says what they train."""
    batch, explicit = collector_batch(cfg), set(explicit)
    t = cfg.train
    errors = []
    for name in BATCHED_FIELDS:
        value = int(getattr(t, name.split(".")[1]))
        if name not in explicit or value <= 0 or batch <= 0 or value % batch == 0:
            continue
        nearest = [v for v in (value // batch * batch, (value // batch + 1) * batch) if v > 0]
        errors.append(
            f"{name}={value}: not a whole number of collector batches of {batch} env steps "
            f"(train.num_envs={t.num_envs} x {_max_steps(cfg)[0]}={_max_steps(cfg)[1]}); "
            f"the nearest exact values: {' or '.join(map(str, nearest))}"
        )
    return errors


def rounding_notes(batch: int, total_env_steps: int, eval_interval: int) -> list[str]:
    """One line each for the run's log on a length or interval that is not a whole number of batches of
    ``batch`` env steps, so the rounding is never silent."""
    notes = []
    for name, value in (("train.total_env_steps", total_env_steps), ("train.eval_interval", eval_interval)):
        if value > 0 and batch > 0 and value % batch:
            if name == "train.total_env_steps":
                what = f"trains {-(-value // batch) * batch:,} env steps"
            else:  # evaluated at the first batch end at or after each multiple of the interval
                steps = ", ".join(f"{-(-k * value // batch) * batch:,}" for k in (1, 2, 3))
                what = f"evaluates at the first batch end at or after each multiple of it: env steps {steps}, ..."
            notes.append(
                f"{name}={value} is not a whole number of collector batches of {batch} env steps: the run {what}"
            )
    return notes
