"""Hand-made baseline policies behind one interface (see :class:`~mcrs.policies.base.Policy`)."""

from __future__ import annotations

from mcrs.env.config import EnvConfig
from mcrs.policies.base import Policy
from mcrs.policies.greedy import GreedyPolicy
from mcrs.policies.lawnmower import LawnmowerPolicy
from mcrs.policies.random_policy import RandomPolicy

POLICIES: dict[str, type[Policy]] = {
    "random": RandomPolicy,
    "lawnmower": LawnmowerPolicy,
    "greedy": GreedyPolicy,
}


def make_policy(name: str, env_config: EnvConfig, seed: int = 0) -> Policy:
    """Build the named policy for ``env_config``; its random choices follow ``seed``."""
    if name not in POLICIES:
        raise ValueError(f"unknown policy {name!r}; allowed: {sorted(POLICIES)}")
    return POLICIES[name](env_config, seed)


__all__ = ["POLICIES", "GreedyPolicy", "LawnmowerPolicy", "Policy", "RandomPolicy", "make_policy"]
