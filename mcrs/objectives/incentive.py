"""EMU's episodic incentive (Na et al. 2024) as strategy objects, chosen once from ``algo.incentive``.

The memory asks the strategy which episodes are desirable (:meth:`Incentive.desirable`) and the TD loss
asks it for ``r_p`` (:meth:`Incentive.reward`), so neither branches on the name::

    none     Incentive()             no incentive (every algorithm but EMU)
    fixed    FixedThreshold(R_thr)   desirable: return >= R_thr; r_p = gamma * N_xi/N_call * max(H - Q', 0)
    change   EvaluationThreshold()   desirable: return >= the latest evaluation return; r_p = gamma * max(H - Q', 0)

Here ``H = H(phi(s_{t+1}))`` and ``Q' = Q_tot_target(s_{t+1})`` on memory hits, 0 on misses."""

from __future__ import annotations

from collections.abc import Callable

import torch

from mcrs.choices import INCENTIVES


class Incentive:
    """No incentive: the base of the strategies.

    Attributes:
        name: the ``algo.incentive`` value it stands for.
        reads_memory: whether :meth:`reward` needs ``memory_return`` and ``memory_hit``.
        in_keys: further batch keys it reads, by their ``ValueFactorisationLoss.tensor_keys`` names.
        tracks_desirability: whether the memory counts N_xi / N_call.
    """

    name: str = "none"
    reads_memory: bool = False
    in_keys: tuple[str, ...] = ()
    tracks_desirability: bool = False

    def desirable(self, returns: torch.Tensor, last_eval_reward: float | None) -> torch.Tensor | None:
        """Return which episodes (returns ``[E]``) are desirable as bool ``[E]``, or None."""
        return None

    def reward(
        self,
        memory_return: torch.Tensor | None,
        hit: torch.Tensor | None,
        next_value: torch.Tensor,
        gamma: float,
        read: Callable[[str], torch.Tensor],
    ) -> torch.Tensor | None:
        """Return the incentive ``r_p`` ``[B, T, 1]`` added to the TD target, or None.

        Args:
            memory_return: ``H(phi(s_{t+1}))`` ``[B, T, 1]``; None unless ``reads_memory``.
            hit: 1 on a memory hit of a real transition, else 0, ``[B, T, 1]``.
            next_value: the target network's ``Q_tot(s_{t+1})`` ``[B, T, 1]``.
            read: the batch's transitions at a key of ``in_keys``.
        """
        return None

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


class FixedThreshold(Incentive):
    """EMU: episodes with a return >= ``threshold`` are desirable; ``r_p`` is scaled by N_xi / N_call."""

    name = "fixed"
    reads_memory = True
    in_keys = ("memory_ratio",)
    tracks_desirability = True

    def __init__(self, threshold: float) -> None:
        self.threshold = float(threshold)

    def desirable(self, returns: torch.Tensor, last_eval_reward: float | None) -> torch.Tensor:
        return returns >= self.threshold

    def reward(self, memory_return, hit, next_value, gamma, read) -> torch.Tensor:
        gap = (memory_return - next_value).clamp(min=0.0) * hit
        return gamma * (gap * read("memory_ratio"))

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.threshold:g})"


class EvaluationThreshold(Incentive):
    """EMU-change: the threshold is the latest greedy evaluation's return, and ``r_p`` drops the N_xi / N_call
    factor."""

    name = "change"
    reads_memory = True
    tracks_desirability = True

    def desirable(self, returns: torch.Tensor, last_eval_reward: float | None) -> torch.Tensor:
        return returns >= (float("inf") if last_eval_reward is None else last_eval_reward)

    def reward(self, memory_return, hit, next_value, gamma, read) -> torch.Tensor:
        return gamma * ((memory_return - next_value).clamp(min=0.0) * hit)


#: ``algo.incentive`` -> its strategy (each built with the config's ``algo.incentive_threshold``).
INCENTIVE_TYPES: dict[str, Callable[[float], Incentive]] = {
    "none": lambda threshold: Incentive(),
    "fixed": FixedThreshold,
    "change": lambda threshold: EvaluationThreshold(),
}


def make_incentive(name: str | Incentive, threshold: float = 365.0) -> Incentive:
    """Return the strategy named ``name``; an :class:`Incentive` is returned as it is."""
    if isinstance(name, Incentive):
        return name
    if name not in INCENTIVE_TYPES:
        raise ValueError(f"incentive must be one of {', '.join(INCENTIVES)}, got {name!r}")
    return INCENTIVE_TYPES[name](threshold)
