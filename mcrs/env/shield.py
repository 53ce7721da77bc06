"""The safety shields: masks of the moves a penalty would charge, as a safety layer under a deployed policy.

Both shields are scenario options beyond the paper, off by default. A UAV whose every move a shield would
mask keeps the mask it had before that shield, so the mask never empties.

``no_fly_shield`` masks exactly the moves that r3 would charge: a (UAV, zone) pair closer than d1
(``no_fly_safety``) after the move, compared as ``safety_rule`` says. Zones are static within an episode,
so the table of safe moves is built once per episode and each step is one gather.

``uav_shield`` is a right of way against r4. UAVs move at once and every action is a move, so two UAVs
collide only by moving into the same place together. Each UAV gives way to the lower-indexed UAVs in its
sight: a move is masked if it could end where r4 charges with any on-grid move of such a UAV. UAV 0 never
gives way, and two UAVs in sight of each other cannot collide. It is the coverage heuristic's rule
(mcrs/policies/coverage.py) made hard, and each UAV needs only its own observation."""

from __future__ import annotations

import math

import torch

from mcrs.env.config import EnvConfig


def safe_move_table(
    no_fly_pos: torch.Tensor, moves: torch.Tensor, mask_of_cell: torch.Tensor, config: EnvConfig
) -> torch.Tensor:
    """Return ``[M, C, 8]`` bool: move ``a`` from cell ``c`` stays on the grid and ends where r3 charges
    nothing. ``no_fly_pos`` is ``[M, Z, 2]``, ``moves`` ``[8, 2]`` and ``mask_of_cell`` ``[C, 8]`` (on-grid
    moves)."""
    cells, height, d1 = mask_of_cell.shape[0], config.height, config.no_fly_safety
    cell = torch.arange(cells, device=no_fly_pos.device)
    xy = torch.stack([cell // height, cell % height], dim=-1)  # [C, 2]
    destination = xy.unsqueeze(1) + moves  # [C, 8, 2], off-grid entries are masked anyway
    offset = destination.view(1, cells, -1, 1, 2) - no_fly_pos.view(no_fly_pos.shape[0], 1, 1, -1, 2)
    squared = offset.pow(2).sum(-1)  # [M, C, 8, Z]
    near = config.violates(squared, d1).any(-1)  # exact: integers compared with a float threshold
    return mask_of_cell.unsqueeze(0) & ~near


def shielded_mask(safe_moves: torch.Tensor, cell: torch.Tensor, unshielded: torch.Tensor) -> torch.Tensor:
    """Return the ``[E, N, 8]`` safe moves of the UAVs on ``cell``, or ``unshielded`` where none is safe."""
    safe = safe_moves.gather(1, cell.unsqueeze(-1).expand(-1, -1, safe_moves.shape[-1]))
    return torch.where(safe.any(-1, keepdim=True), safe, unshielded)


class RightOfWay:
    """The ``uav_shield`` mask of a step, as lookups in one table built at construction.

    Whether UAV i's move a may meet one of UAV j's on-grid moves depends only on the offset ``pos_i -
    pos_j``, on a, and on j's grid mask as a byte: ``table[offset, a, byte]``. Offsets too far apart to
    meet share one all-False row, so a step is a gather over the UAV pairs rather than a test of their 8 x
    8 moves."""

    def __init__(self, moves: torch.Tensor, config: EnvConfig) -> None:
        d2, dev = config.uav_safety, moves.device
        span = max(config.width, config.height) - 1  # no offset on the grid is larger
        self.radius = min(span, math.ceil(d2) + 2) if math.isfinite(d2) else span
        side = 2 * self.radius + 1
        ticks = torch.arange(-self.radius, self.radius + 1, device=dev)
        offset = torch.stack(torch.meshgrid(ticks, ticks, indexing="ij"), -1).view(
            -1, 1, 1, 2
        )  # [O, 1, 1, 2]
        gap = offset + moves.view(1, 8, 1, 2) - moves.view(1, 1, 8, 2)  # [O, a, b, 2]
        close = config.violates(gap.pow(2).sum(-1).to(torch.float32), d2).to(torch.float32)  # [O, 8, 8]
        self.action = torch.arange(8, device=dev)
        self.bit = 2**self.action
        allowed = (torch.arange(256, device=dev).unsqueeze(-1) & self.bit).ne(0).to(torch.float32)  # [256, b]
        meets = (close @ allowed.T).gt(0)  # [O, a, 256]
        self.table = torch.cat([meets, meets.new_zeros(1, 8, 256)]).view(-1)  # the last row: too far apart
        self.far, self.side = side * side, side
        self.sight_squared = config.sight_range**2

    def mask(
        self,
        mask: torch.Tensor,
        on_grid: torch.Tensor,
        uav_pos: torch.Tensor,
        uav_squared: torch.Tensor,
        earlier: torch.Tensor,
    ) -> torch.Tensor:
        """Return ``mask`` less the moves of UAV i that could meet an on-grid move of a lower-indexed UAV in
        its sight.

        A UAV left with no move keeps ``mask``. ``on_grid`` ``[E, N, 8]`` is all that i can tell of j's
        moves, since j's no-fly mask depends on zones i may not see. ``uav_squared`` ``[E, N, N]`` holds
        squared distances and ``earlier[i, j]`` is j < i."""
        offset = uav_pos.unsqueeze(2) - uav_pos.unsqueeze(1)  # [E, i, j, 2]: pos_i - pos_j
        near = offset.abs().amax(-1) <= self.radius
        gives_way = earlier & (uav_squared <= self.sight_squared) & near
        row = (offset[..., 0] + self.radius) * self.side + offset[..., 1] + self.radius
        row = torch.where(gives_way, row, self.far)  # [E, i, j]
        byte = (on_grid.to(torch.int64) * self.bit).sum(-1)  # [E, j]
        cell = (row * 8).unsqueeze(-1) + self.action  # [E, i, j, a]
        conflict = self.table[cell * 256 + byte.unsqueeze(1).unsqueeze(-1)].any(2)  # [E, i, a]
        safe = mask & ~conflict
        return torch.where(safe.any(-1, keepdim=True), safe, mask)
