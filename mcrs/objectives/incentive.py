"""EMU's episodic incentive (Na et al. 2024) as strategy objects, chosen once from ``algo.incentive``.

One object serves both ends: the episodic memory asks it which collected episodes are desirable
(:meth:`Incentive.desirable`, which feeds the memory's N_xi / N_call counts), the TD loss asks it for the
incentive ``r_p`` added to its target (:meth:`Incentive.reward`). So neither the loss nor the memory's
callback branches on the incentive's name::

    none     Incentive()             no incentive (every algorithm but EMU)
    fixed    FixedThreshold(R_thr)   desirable: return >= R_thr; r_p = gamma * N_xi/N_call * max(H - Q', 0)
    change   EvaluationThreshold()   desirable: return >= the latest evaluation return; r_p = gamma * max(H - Q', 0)

with ``H = H(phi(s_{t+1}))`` the memory's value and ``Q' = Q_tot_target(s_{t+1})`` on memory hits (0 on
misses). A new incentive subclasses :class:`Incentive` and overrides the two methods (and ``in_keys`` if it
reads more of the batch); an algorithm hands it to the loss and the memory (``mcrs.experiment.training.algorithms``).
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from mcrs.choices import INCENTIVES


class Incentive:
    """No incentive: the base of the strategies, and the strategy of every algorithm but EMU.

    Attributes:
        name: the ``algo.incentive`` value it stands for.
        reads_memory: whether :meth:`reward` needs the memory's look-ups (``memory_return``, ``memory_hit``).
        in_keys: the further batch keys it reads, by their ``ValueFactorisationLoss.tensor_keys`` names.
        tracks_desirability: whether the memory counts N_xi / N_call (episodes marked by :meth:`desirable`).
    """

    name: str = "none"
    reads_memory: bool = False
    in_keys: tuple[str, ...] = ()
    tracks_desirability: bool = False

    def desirable(self, returns: torch.Tensor, last_eval_reward: float | None) -> torch.Tensor | None:
        """Which episodes (returns ``[E]``) are desirable (bool ``[E]``); ``None``: no episode is marked."""
        return None

    def reward(
        self,
        memory_return: torch.Tensor | None,
        hit: torch.Tensor | None,
        next_value: torch.Tensor,
        gamma: float,
        read: Callable[[str], torch.Tensor],
    ) -> torch.Tensor | None:
        """The incentive ``r_p`` ``[B, T, 1]`` added to the TD target, or ``None`` for none.

        Args:
            memory_return: ``H(phi(s_{t+1}))`` ``[B, T, 1]`` (``None`` unless ``reads_memory``).
            hit: the memory hits as weights ``[B, T, 1]``: 1 on a hit of a real transition, else 0.
            next_value: the target network's ``Q_tot(s_{t+1})`` ``[B, T, 1]``.
            gamma: the discount.
            read: the batch's transitions at a key of ``in_keys`` (``read("memory_ratio")`` ``[B, T, 1]``).
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
    """EMU-change: the threshold is the latest greedy evaluation's return (none before the first: no
    episode is desirable), and ``r_p`` drops the N_xi / N_call factor."""

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
    """The strategy of ``algo.incentive`` ``name`` (an :class:`Incentive` is returned as it is)."""
    if isinstance(name, Incentive):
        return name
    if name not in INCENTIVE_TYPES:
        raise ValueError(f"incentive must be one of {', '.join(INCENTIVES)}, got {name!r}")
    return INCENTIVE_TYPES[name](threshold)
