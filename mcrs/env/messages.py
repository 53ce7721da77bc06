"""Communication delay and per-link bandwidth (``comm_delay``, ``comm_budget``), variants beyond the paper.

A message to UAV i carries, per source UAV q, a level: "q's first k detections". Under max-plus-sum fusion
(eq. 11) that is all a count map N^{j,q} says, since q's own counts only grow. Merging messages is a max of
levels, so a late message never undoes newer knowledge and the fast form of :mod:`mcrs.env.fusion` stays
exact."""

from __future__ import annotations

import torch

from mcrs.env.config import EnvConfig
from mcrs.env.fusion import fuse_known, reachable_within


def budgeted_round(
    known: torch.Tensor, neighbours: torch.Tensor, remaining: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Run one synchronous round in which link j -> i carries at most ``remaining[e, i, j]`` detections.

    UAV i lacks ``backlog[q] = max(known[j, q] - known[i, q], 0)`` of source q's detections that j holds.
    The link serves the sources with the largest backlog first, ties to the lower index, each source oldest
    first, until the budget is spent (docs/ENVIRONMENT.md). What i receives is merged by max (eq. 11). Only
    linked pairs are computed, and the ranking uses comparison masks because a sort of 10 values is far
    slower on CPU.

    Args:
        known: ``[E, N, N]`` levels before the round.
        neighbours: ``[E, N, N]`` bool, ``[e, i, j]``: i hears j this round.
        remaining: ``[E, N, N]`` float32, what link j -> i may still carry this step; updated in place.

    Returns:
        The levels after the round and the budgets left.
    """
    n_envs, n_uavs, _ = known.shape
    env, receiver, sender = neighbours.nonzero().unbind(-1)
    if env.numel() == 0:
        return known, remaining
    levels = known.to(torch.float32)  # small integers: exact
    mine, theirs = levels[env, receiver], levels[env, sender]  # [P, N] over sources q
    backlog = (theirs - mine).clamp(min=0)
    budget = remaining[env, receiver, sender]
    total = backlog.sum(-1)
    sent = backlog.clone()  # links whose whole backlog fits send it all
    over = (total > budget).nonzero().squeeze(-1)
    if over.numel():
        sent[over] = _within_budget(backlog[over], budget[over])
    remaining[env, receiver, sender] = budget - sent.sum(-1)
    merged = levels.view(n_envs * n_uavs, n_uavs).clone()
    rows = (env * n_uavs + receiver).unsqueeze(-1).expand(-1, n_uavs)
    merged.scatter_reduce_(0, rows, mine + sent, "amax", include_self=True)
    return merged.view_as(known).to(known.dtype), remaining


def _within_budget(backlog: torch.Tensor, budget: torch.Tensor) -> torch.Tensor:
    """Return what over-budget links send: the largest backlog first, ties to the lower source."""
    n_uavs = backlog.shape[-1]
    # ahead[p, q]: detections the link sends before source q's = backlog of every source ranked before q.
    other, this = backlog.unsqueeze(-2), backlog.unsqueeze(-1)  # [P, 1, q'], [P, q, 1]
    lower = torch.ones(n_uavs, n_uavs, dtype=torch.bool, device=backlog.device).tril(-1)  # [q, q']: q' < q
    ranked_before = (other > this) | ((other == this) & lower)
    ahead = torch.matmul(ranked_before.to(torch.float32), backlog.unsqueeze(-1)).squeeze(-1)
    return torch.minimum(backlog, (budget.unsqueeze(-1) - ahead).clamp(min=0))


class MessageChannel:
    """The exchange of one step under ``comm_delay`` and/or ``comm_budget``, batched over environments.

    A step first delivers the messages sent ``comm_delay`` steps ago, then composes this step's messages
    over this step's neighbour graph with ``comm_rounds`` relay rounds. ``in_flight[e, slot, i, q]`` holds
    the level of q that i will receive from the message sent at step s with ``s % comm_delay == slot``."""

    def __init__(self, config: EnvConfig, known_dtype: torch.dtype, device: torch.device) -> None:
        E, N = config.num_envs, config.n_uavs
        self.delay, self.budget, self.rounds = config.comm_delay, config.comm_budget, config.rounds_per_step
        self.in_flight = (
            torch.zeros(E, self.delay, N, N, dtype=known_dtype, device=device) if self.delay > 0 else None
        )
        self._env_index = torch.arange(E, device=device)

    def tensors(self) -> list[torch.Tensor]:
        """Return the episode state it holds: the messages in flight."""
        return [] if self.in_flight is None else [self.in_flight]

    def clear(self, envs: torch.Tensor) -> None:
        """Drop the messages in flight of the new episodes in ``envs``."""
        if self.in_flight is not None:
            self.in_flight[envs] = 0

    def communicate(self, known: torch.Tensor, neighbours: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
        """Deliver, then send; return the levels known after step ``step`` ``[E]``."""
        if self.in_flight is not None:
            slot = step % self.delay
            known = torch.maximum(known, self.in_flight[self._env_index, slot])
        sent = self._exchange(known, neighbours)
        if self.in_flight is None:
            return sent
        self.in_flight[self._env_index, slot] = sent
        return known

    def _exchange(self, known: torch.Tensor, neighbours: torch.Tensor) -> torch.Tensor:
        """Return the levels each UAV holds after this step's rounds."""
        if self.budget is None:
            return fuse_known(known, reachable_within(neighbours, self.rounds))
        # The budget is per link direction and per step, shared by the step's rounds.
        remaining = torch.full(neighbours.shape, float(self.budget), device=known.device)
        for _ in range(self.rounds):  # bounded by the config (comm_rounds, or N - 1 for flood)
            known, remaining = budgeted_round(known, neighbours, remaining)
        return known
