"""The no-fly safety shield (scenario option ``no_fly_shield``): mask the moves that would cost r3.

Reward term r3 charges ``w_no_fly`` for every (UAV, zone) pair closer than ``no_fly_safety`` (d1) after a
move (``safety_rule``: ``enter``, the default, charges distances < d1, i.e. the zone's own cell at d1 = 1;
``near`` charges distances <= d1). The shield masks exactly the moves that r3 would charge.
The shield removes such moves from the action mask, so that every policy that respects the mask (learners,
their exploration, the heuristics) cannot take them. Zones are static within an episode, so the table of
safe moves is built once per environment when its episode starts; each step is then one gather.
A UAV whose every on-grid move is unsafe keeps its unshielded mask: the mask never empties.
"""

from __future__ import annotations

import torch

from mcrs.env.config import EnvConfig


def safe_move_table(
    no_fly_pos: torch.Tensor, moves: torch.Tensor, mask_of_cell: torch.Tensor, config: EnvConfig
) -> torch.Tensor:
    """``[M, C, 8]`` bool: move ``a`` from cell ``c`` stays on the grid and ends where r3 charges nothing.

    ``no_fly_pos`` is ``[M, Z, 2]`` (cells ``(x, y)``), ``moves`` ``[8, 2]``, ``mask_of_cell`` ``[C, 8]``
    (on-grid moves); d1 is ``config.no_fly_safety``, compared by ``config.violates`` as the reward does.
    """
    cells, height, d1 = mask_of_cell.shape[0], config.height, config.no_fly_safety
    cell = torch.arange(cells, device=no_fly_pos.device)
    xy = torch.stack([cell // height, cell % height], dim=-1)  # [C, 2]
    destination = xy.unsqueeze(1) + moves  # [C, 8, 2], off-grid entries are masked anyway
    offset = destination.view(1, cells, -1, 1, 2) - no_fly_pos.view(no_fly_pos.shape[0], 1, 1, -1, 2)
    squared = offset.pow(2).sum(-1)  # [M, C, 8, Z]
    near = config.violates(squared, d1).any(-1)  # exact: integers compared with a float threshold
    return mask_of_cell.unsqueeze(0) & ~near


def shielded_mask(safe_moves: torch.Tensor, cell: torch.Tensor, unshielded: torch.Tensor) -> torch.Tensor:
    """``[E, N, 8]`` mask of the UAVs on ``cell`` ``[E, N]``: the safe moves, or ``unshielded`` where none is."""
    safe = safe_moves.gather(1, cell.unsqueeze(-1).expand(-1, -1, safe_moves.shape[-1]))
    return torch.where(safe.any(-1, keepdim=True), safe, unshielded)
