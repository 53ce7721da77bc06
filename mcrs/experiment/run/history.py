"""What the old forms of checkpoints, configs and records meant, and how this mcrs reads them.

Code that reads an old form carries a one-line pointer to :data:`OLD_FORMS` here. The scenario's old forms
are :data:`mcrs.env.config.LEGACY_SCENARIO_VALUES`, since the env layer imports nothing above it.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from mcrs.env.config import with_legacy_values

#: Each old form, by a short name, and what it meant; the code that reads it names the key.
OLD_FORMS = {
    # checkpoints (last.pt, model_<steps>.pt, replay block files)
    "before callbacks": (
        "written by a pre-release mcrs: the episodic memory under 'episodic' and EMC's curiosity inside the "
        "learner's state, with no 'callbacks' entry. Such a run cannot be resumed and is refused "
        "(before_callbacks); weights files have no callbacks and pass. prune_bulk still drops "
        "'episodic.memory'."
    ),
    "no checksum": "written before entry checksums: read unverified, said once per folder in the run's log.",
    "no fingerprint": (
        "written before fingerprints: the fingerprint is derived from the config and weights it holds."
    ),
    "no task in the fingerprint": (
        "written before tasks: the run is MCRS on config.env. An MCRS run's config.yaml still has no "
        "'task' key, so that old and new configs read alike."
    ),
    "config field on one side only": (
        "a field added to or dropped from the schema since the checkpoint: skipped when fingerprints are "
        "compared. An algo.options.* setting the checkpoint lacks resumes at its default, said in the log."
    ),
    "inline replay": "'replay' holds the episodes: written before the block files (last_good.pt still is).",
    "unfingerprinted replay blocks": (
        "a manifest without 'fingerprinted': its blocks were written before they carried fingerprints."
    ),
    "learner without 'loss'": (
        "written before the loss module's state was saved whole: 'agent', 'mixer', 'target_agent' and "
        "'target_mixer' are loaded one by one."
    ),
    "callback state under 'callback'": (
        "a Callback subclass without its own name saved its state as 'callback' before callbacks were "
        "named after their class; the refusal tells the user to set name = 'callback'."
    ),
    "no last_eval_step": (
        "written before checkpoints named their last evaluation's step (LEGACY_EVAL_STEP): whether the "
        "final evaluation was done is read from the evaluation log (final_evaluation_from_log)."
    ),
    "no logs.rows": (
        "written before checkpoints counted the rows of each CSV log: a resume keeps the rows logged at or "
        "before the checkpoint's env step."
    ),
    # configs and records
    "env runtime fields": "num_envs and device were once saved under 'env' (current_config drops them).",
    "flat module names": (
        "the modules of mcrs.experiment were once all at its top (mcrs.experiment.trainer); fingerprints "
        "keep those names (class_path)."
    ),
}

#: The rooms of :mod:`mcrs.experiment` (:data:`OLD_FORMS`, "flat module names").
ROOMS = ("util", "run", "training", "commands")

#: ``last_eval_step`` of a checkpoint without that entry (:data:`OLD_FORMS`, "no last_eval_step").
LEGACY_EVAL_STEP = -1

#: Algorithm fields added after runs were saved, with the value such a saved run was trained with.
LEGACY_ALGO_VALUES = {"time_limit": "bootstrap"}


#: Why a checkpoint in the layout :func:`before_callbacks` detects is refused, after its path.
BEFORE_CALLBACKS_REFUSAL = (
    "was written by a pre-release mcrs (its memory and curiosity are not in 'callbacks'); it cannot be "
    "resumed: start a new run"
)


def before_callbacks(state: dict[str, Any]) -> bool:
    """Whether a checkpoint's ``state`` is in the layout from before callbacks (:data:`OLD_FORMS`)."""
    learner = state.get("learner")
    old = "episodic" in state or (isinstance(learner, dict) and "curiosity" in learner)
    return old and "callbacks" not in state


def class_path(cls: type) -> str:
    """The dotted name by which a fingerprint records a class.

    A class in a room of :mod:`mcrs.experiment` keeps its flat name (``mcrs.experiment.algorithms.QMIX``),
    so that older checkpoints and records still match."""
    parts = cls.__module__.split(".")
    if len(parts) == 4 and parts[:2] == ["mcrs", "experiment"] and parts[2] in ROOMS:
        parts = [*parts[:2], parts[3]]
    return ".".join([*parts, cls.__qualname__])


def current_config(config: dict[str, Any]) -> dict[str, Any]:
    """A saved config in today's layout.

    The env's runtime fields go, and the fields the config predates (``env.safety_rule``,
    ``algo.time_limit``) take the values it was made under (:func:`legacy_values` lists them)."""
    if not isinstance(config.get("env"), dict):
        return config
    env = {k: v for k, v in config["env"].items() if k not in ("num_envs", "device")}
    env, _ = with_legacy_values(env)
    out = {**config, "env": env}
    if isinstance(config.get("algo"), dict):
        out["algo"] = {**LEGACY_ALGO_VALUES, **config["algo"]}
    return out


def legacy_values(config: dict[str, Any]) -> list[str]:
    """The fields a saved config predates, as :func:`current_config` sets them (``["env.safety_rule=near"]``).

    Empty for a config saved by this mcrs."""
    notes: list[str] = []
    if isinstance(config.get("env"), dict):
        notes += [f"env.{line}" for line in with_legacy_values(config["env"])[1]]
    if isinstance(config.get("algo"), dict):
        notes += [f"algo.{k}={v}" for k, v in LEGACY_ALGO_VALUES.items() if k not in config["algo"]]
    return notes


def final_evaluation_from_log(
    run_dir: Path, checkpoint: Path, rows: int | None, env_steps: int, has_eval: bool
) -> bool:
    """Whether a checkpoint without ``last_eval_step`` holds the run's final evaluation.

    It does when the last of the ``rows`` rows its evaluation log had is at ``env_steps``. Without that
    log, ``has_eval`` (whether it holds an evaluation) decides."""
    log = run_dir / "logs" / "scalars" / "eval" / "episode_reward.csv"
    if not rows or not log.is_file():
        return has_eval
    logging.getLogger("mcrs.run").info(  # the run's text log (mcrs.experiment.run.logging.RUN_LOG)
        "%s",
        f"{checkpoint} was written before checkpoints named their last evaluation's step: judged by {log}",
    )
    with open(log) as f:
        kept = [line for line in f.read().splitlines() if line][:rows]
    try:
        return bool(kept) and float(kept[-1].split(",")[0]) == env_steps
    except ValueError:
        return has_eval
