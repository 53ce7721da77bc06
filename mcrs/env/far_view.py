"""Beyond the paper: a coarse view of the UAV's own fused map past its 8 neighbours (``env.far_view``).

The paper's observation (eqs. 18-21) holds the UAV's fused m(U) only at the 8 cells around it, so late in an
episode, stranded in read ground, a UAV cannot see where the unread cells are (docs/DIAGNOSTICS.md). With
``far_view = k > 0`` the observation gains 8 values, one per move in action order (``MOVES``): the mean of the
UAV's own fused m(U) over the square window of side ``2k + 1`` centred ``k + 1`` cells away in that move's
direction (cells off the grid count 0, as in the 8-cell block). The windows of neighbouring directions
overlap; together they cover every cell within ``2k + 1`` steps (Chebyshev) of the UAV.

One box filter over all UAVs' maps and one gather per step, batched over environments and UAVs.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from mcrs.env.config import EnvConfig


class FarView:
    """The 8 window means of own m(U) that ``far_view = k`` appends to every observation."""

    def __init__(self, config: EnvConfig, moves: torch.Tensor) -> None:
        k = int(config.far_view)
        if k < 1:
            raise ValueError(f"far_view={config.far_view!r}: FarView needs k >= 1 (0 is the paper's view)")
        self.k = k
        # A map padded by 2k + 1 zeros on each side and box-filtered without padding has one mean for every
        # centre from -(k + 1) to L + k along each axis, at index centre + k + 1: every centre a UAV asks for.
        self.pad = 2 * k + 1
        self.pooled_height = config.height + 2 * k + 2
        self.offsets = moves * (k + 1) + (k + 1)  # [8, 2]: index of each window's centre, less the position

    def means(self, unknown: torch.Tensor, position: torch.Tensor) -> torch.Tensor:
        """``[E, N, 8]`` window means, from own m(U) maps ``[E, N, W, H]`` and positions ``[E, N, 2]``."""
        E, N, W, H = unknown.shape
        padded = F.pad(unknown.reshape(E * N, 1, W, H), (self.pad,) * 4)
        pooled = F.avg_pool2d(
            padded, kernel_size=2 * self.k + 1, stride=1
        )  # [E N, 1, W + 2k + 2, H + 2k + 2]
        centre = position.unsqueeze(2) + self.offsets  # [E, N, 8, 2]
        index = (centre[..., 0] * self.pooled_height + centre[..., 1]).view(E * N, 8)
        return pooled.view(E * N, -1).gather(1, index).view(E, N, 8)
