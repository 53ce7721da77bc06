"""Communication and max-plus-sum fusion of detection counts (paper eqs. 10-11).

:class:`DirectFusion` applies the paper's rule literally: every UAV keeps every UAV's count maps N^{i,q},
takes the max over neighbours and sums over q. It is the test oracle, with memory O(N^2 L1 L2).

The environment uses a fast form. A UAV's own counts only grow, so N^{i,q} is always q's map as of an
earlier step, and it is enough to know how many of q's detections UAV i has heard of, ``known[i, q]``. A
round is ``known[i, q] <- max_j known[j, q]`` over i and its neighbours, and :func:`apply_new_detections`
adds the newly learned detections from the per-step log. Memory is O(N L1 L2 + T N). Delayed and
bandwidth-limited messages (:mod:`mcrs.env.messages`) keep this form exact."""

from __future__ import annotations

import torch


def neighbours_within(squared_distance: torch.Tensor, comm_range: float) -> torch.Tensor:
    """Return neighbours ``[..., i, j]``: ``||u_j - u_i|| < comm_range`` and ``j != i``. It compares squared
    distances, which is exact for integer cells."""
    eye = torch.eye(squared_distance.shape[-1], dtype=torch.bool, device=squared_distance.device)
    return (squared_distance < comm_range**2) & ~eye


def neighbour_graph(positions: torch.Tensor, comm_range: float) -> torch.Tensor:
    """Neighbours ``[..., i, j]`` of UAVs at integer cells ``positions`` ``[..., N, 2]``."""
    delta = positions.unsqueeze(-2) - positions.unsqueeze(-3)
    return neighbours_within(delta.square().sum(-1).to(torch.float32), comm_range)


def reachable_within(neighbours: torch.Tensor, rounds: int) -> torch.Tensor:
    """Return who hears whom after ``rounds`` synchronous rounds: walks of length <= rounds, self included.
    Max is associative, so ``rounds`` rounds of "max over myself and my neighbours" equal one max over this
    set. It takes log2(rounds) boolean matrix products."""
    n = neighbours.shape[-1]
    step = neighbours | torch.eye(n, dtype=torch.bool, device=neighbours.device)
    if rounds == 1:
        return step
    rounds = min(rounds, n - 1) if n > 1 else 1
    result = None
    power = step.to(torch.float32)
    while rounds:
        if rounds & 1:
            result = power if result is None else (torch.matmul(result, power) > 0).to(torch.float32)
        rounds >>= 1
        if rounds:
            power = (torch.matmul(power, power) > 0).to(torch.float32)
    return result > 0


def fuse_known(known: torch.Tensor, reach: torch.Tensor) -> torch.Tensor:
    """``known[..., i, q] <- max over j reachable from i of known[..., j, q]`` (counts are >= 0)."""
    # [..., i, q, j]: the reduction runs over the last, contiguous dimension; a product of non-negative
    # counts with 0/1 is cheaper than torch.where here.
    spread = reach.unsqueeze(-2).to(known.dtype) * known.transpose(-1, -2).unsqueeze(-3)
    return spread.amax(dim=-1)


def apply_new_detections(
    counts: torch.Tensor,
    known_before: torch.Tensor,
    known_after: torch.Tensor,
    log_channel_cell: torch.Tensor,
    step_weight: torch.Tensor | None = None,
) -> None:
    """Add to ``counts`` every detection that UAV i learned of between the two ``known`` tables.

    The work is proportional to the number of newly learned detections, never to N^2 L1 L2.

    Args:
        counts: ``[E, N, 2 * C]``, UAV i's summed count maps indexed ``cell * 2 + channel``; updated in place.
        known_before, known_after: ``[E, N, N]`` int, how many detections of q UAV i knows.
        log_channel_cell: ``[E, T + 1, N]``, the flat ``cell * 2 + channel`` of q's detection at step s.
        step_weight: ``[T + 1]``, what a detection of step s adds under ``evidence_decay``; None adds 1.
    """
    n_uavs = known_before.shape[-1]
    log_steps = log_channel_cell.shape[1]
    gained = known_after - known_before
    # (env, learner i, source q) of every pair that learned something: nonzero gives the coordinates
    # directly, which is cheaper than dividing flat indices.
    env, learner, source = gained.nonzero().unbind(-1)
    if env.numel() == 0:
        return
    pairs = (env * n_uavs + learner) * n_uavs + source
    lengths = gained.reshape(-1)[pairs].long()
    # Per pair: where its new detections start in the log, and where they are counted.
    first_step = known_before.reshape(-1)[pairs].long()
    item_start = torch.cumsum(lengths, 0) - lengths  # position of each pair's first item
    log_base = (env * log_steps + first_step) * n_uavs + source - item_start * n_uavs
    count_base = (env * n_uavs + learner) * counts.shape[-1]
    # One item per newly learned detection; item k of a pair reads log step first_step + k.
    item_pair = torch.repeat_interleave(lengths)
    item_offset = torch.arange(0, item_pair.numel() * n_uavs, n_uavs, device=counts.device)  # item * N
    flat_cell = log_channel_cell.reshape(-1)[log_base[item_pair] + item_offset].long()
    target = count_base[item_pair] + flat_cell
    if step_weight is None:
        added = torch.ones_like(target, dtype=counts.dtype)
    else:
        item = torch.arange(item_pair.numel(), device=counts.device)
        added = step_weight[first_step[item_pair] + item - item_start[item_pair]].to(counts.dtype)
    counts.view(-1).scatter_add_(0, target, added)


class DirectFusion:
    """The paper's max-plus-sum rule applied literally; the test oracle for the fast form."""

    def __init__(self, n_envs: int, n_uavs: int, n_cells: int, device: torch.device | str = "cpu") -> None:
        # maps[e, i, q, cell, channel]: what UAV i knows of q's detection counts.
        self.maps = torch.zeros(n_envs, n_uavs, n_uavs, n_cells, 2, dtype=torch.int64, device=device)

    def sense(self, cells: torch.Tensor, readings: torch.Tensor) -> None:
        """Each UAV q adds its reading (True = positive) of ``cells[e, q]`` to its own map N^{q,q}."""
        n_envs, n_uavs = cells.shape
        env = torch.arange(n_envs).unsqueeze(1).expand(n_envs, n_uavs)
        uav = torch.arange(n_uavs).unsqueeze(0).expand(n_envs, n_uavs)
        channel = (~readings).long()
        self.maps[env, uav, uav, cells, channel] += 1

    def exchange(self, neighbours: torch.Tensor) -> None:
        """One synchronous round: N^{i,q} <- max over j in {i} + Ne(i) of N^{j,q}."""
        n = neighbours.shape[-1]
        hears = neighbours | torch.eye(n, dtype=torch.bool)
        before = self.maps.clone()
        for i in range(n):
            heard = before * hears[:, i].view(-1, n, 1, 1, 1)
            self.maps[:, i] = heard.amax(dim=1)

    def summed_counts(self) -> torch.Tensor:
        """``[E, N, C, 2]``: UAV i's fused counts, sum over q of N^{i,q}."""
        return self.maps.sum(dim=2)
