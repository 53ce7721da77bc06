"""Hand-made baseline policies behind one interface (see :class:`~mcrs.policies.base.Policy`)."""

from __future__ import annotations

import logging
from pathlib import Path

from mcrs.env.config import EnvConfig
from mcrs.policies.base import Policy
from mcrs.policies.coverage import CoveragePolicy
from mcrs.policies.greedy import GreedyPolicy
from mcrs.policies.lawnmower import LawnmowerPolicy
from mcrs.policies.random_policy import RandomPolicy

POLICIES: dict[str, type[Policy]] = {
    "random": RandomPolicy,
    "lawnmower": LawnmowerPolicy,
    "greedy": GreedyPolicy,
    "coverage": CoveragePolicy,
}


def make_policy(name: str, env_config: EnvConfig, seed: int = 0) -> Policy:
    """Build the named policy for ``env_config``, its random choices drawn from ``seed``. ``name`` is a
    heuristic (``random``, ``lawnmower``, ``greedy``, ``coverage``), an ``mcrs-train`` checkpoint or run
    directory, or an ``mcrs-export`` file; an agent then acts greedily."""
    # Deferred: the trained and exported agents load TorchRL, which the heuristics do without.
    from mcrs.policies.trained import TrainedPolicy, is_exported, looks_like_checkpoint

    if name not in POLICIES and is_exported(name):
        from mcrs.policies.export import exported_policy

        return exported_policy(name, env_config, seed)
    if name not in POLICIES and looks_like_checkpoint(name):
        return TrainedPolicy.from_checkpoint(name, env_config, seed)
    if name not in POLICIES:
        raise ValueError(
            f"unknown policy {name!r}; allowed: {sorted(POLICIES)}, a checkpoint (.pt file or run directory) "
            "or an exported agent (.pt2)"
        )
    return POLICIES[name](env_config, seed)


def policy_env(name: str, env_config: EnvConfig) -> EnvConfig:
    """Return ``env_config`` as the named policy must play it. A trained agent keeps the observation fields it
    was trained with, such as ``far_view``; the dynamics and rewards are the same. A heuristic plays
    ``env_config`` itself."""
    from mcrs.policies import export, trained

    if name in POLICIES or not trained.looks_like_checkpoint(name):
        return env_config
    settings = export.observation_settings if trained.is_exported(name) else trained.observation_settings
    changed = {k: v for k, v in settings(name).items() if getattr(env_config, k) != v}
    if changed:  # said: an env.far_view=... on the command line does not reach this policy
        logging.getLogger(__name__).warning(
            "%s observes with %s, as it was trained, whatever this evaluation's %s (the task is the same)",
            name,
            ", ".join(f"env.{k}={v}" for k, v in changed.items()),
            ", ".join(f"env.{k}={getattr(env_config, k)}" for k in changed),
        )
    return env_config.replace(**changed) if changed else env_config


def check_policy(name: str, env_config: EnvConfig) -> None:
    """Refuse a checkpoint or exported agent trained on another map or team than ``env_config``. It reads only
    the config, so the ValueError comes before any episode runs."""
    from mcrs.policies import export, trained

    if name in POLICIES or not trained.looks_like_checkpoint(name):
        return
    exported = trained.is_exported(name)
    env = export.trained_env(name) if exported else trained.trained_env(name)
    if env is None:  # loading it names the problem
        return
    own = {field: getattr(env, field) for field in (*trained.OBSERVATION_FIELDS, *trained.TASK_RULES)}
    source = (
        f"exported agent {Path(name).expanduser()}"
        if exported
        else f"checkpoint {trained.resolve_checkpoint(name)}"
    )
    trained.check_playable(env, env_config.replace(**own), source)


__all__ = [
    "POLICIES",
    "CoveragePolicy",
    "GreedyPolicy",
    "LawnmowerPolicy",
    "Policy",
    "RandomPolicy",
    "check_policy",
    "make_policy",
    "policy_env",
]
