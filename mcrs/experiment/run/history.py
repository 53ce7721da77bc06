"""What older forms mean: the compatibility rules for checkpoints, configs and records written by earlier
versions of mcrs.

Each rule says what the old form meant, so that the code that reads it need not. The scenario's own old
forms are :data:`mcrs.env.config.LEGACY_SCENARIO_VALUES` (the env layer imports nothing above it).
"""

from __future__ import annotations

from typing import Any

from mcrs.env.config import with_legacy_values

#: The rooms of :mod:`mcrs.experiment`. Its modules were once all at the top (``mcrs.experiment.trainer``).
ROOMS = ("util", "run", "training", "commands")

#: ``last_eval_step`` of a checkpoint written before that entry existed: the step is read from the eval log.
LEGACY_EVAL_STEP = -1


def class_path(cls: type) -> str:
    """The dotted name by which a fingerprint records a class.

    A class of one of :mod:`mcrs.experiment`'s rooms keeps the flat name it had before the rooms
    (``mcrs.experiment.algorithms.QMIX``, not ``mcrs.experiment.training.algorithms.QMIX``), so that
    checkpoints and records written before them still match."""
    parts = cls.__module__.split(".")
    if len(parts) == 4 and parts[:2] == ["mcrs", "experiment"] and parts[2] in ROOMS:
        parts = [*parts[:2], parts[3]]
    return ".".join([*parts, cls.__qualname__])


#: Algorithm fields added after runs were saved, with the value such a saved run was trained with.
LEGACY_ALGO_VALUES = {"time_limit": "bootstrap"}


def current_config(config: dict[str, Any]) -> dict[str, Any]:
    """A saved config in today's layout: the env's runtime fields were once saved under ``env``, and the
    fields it predates (``env.safety_rule``, ``algo.time_limit``) take the values it was made under
    (:func:`legacy_values` lists them)."""
    if not isinstance(config.get("env"), dict):
        return config
    env = {k: v for k, v in config["env"].items() if k not in ("num_envs", "device")}
    env, _ = with_legacy_values(env)
    out = {**config, "env": env}
    if isinstance(config.get("algo"), dict):
        out["algo"] = {**LEGACY_ALGO_VALUES, **config["algo"]}
    return out


def legacy_values(config: dict[str, Any]) -> list[str]:
    """``["env.safety_rule=near", ...]``: the fields a saved config predates, as :func:`current_config`
    sets them (empty for a config saved by this mcrs)."""
    notes: list[str] = []
    if isinstance(config.get("env"), dict):
        notes += [f"env.{line}" for line in with_legacy_values(config["env"])[1]]
    if isinstance(config.get("algo"), dict):
        notes += [f"algo.{k}={v}" for k, v in LEGACY_ALGO_VALUES.items() if k not in config["algo"]]
    return notes
