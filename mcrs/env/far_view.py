"""A coarse view of the UAV's own fused map beyond its 8 neighbours (``env.far_view``), a variant beyond the
paper.

The paper's observation holds the fused m(U) only at the 8 cells around the UAV, so a UAV stranded in read
ground cannot see where the unread cells are (docs/DIAGNOSTICS.md). With ``far_view = k > 0`` the
observation gains 8 values in action order: the mean of own m(U) over the square window of side ``2k + 1``
centred ``k + 1`` cells away in that move's direction, counting cells off the grid as 0. Together the
windows cover every cell within ``2k + 1`` steps (Chebyshev) of the UAV. Each window is four reads of a
summed-area table."""

from __future__ import annotations

import torch

from mcrs.env.belief import belief_masses
from mcrs.env.config import EnvConfig

#: The m(U) lookup table is built when it has at most this many entries ((N (T + 1) + 1)^2: 16 MB of
#: float32); beyond, and for decayed (float) counts, m(U) is computed from the counts directly.
MAX_TABLE_ENTRIES = 2**22


class FarView:
    """The 8 window means of own m(U) that ``far_view = k`` appends to every observation."""

    def __init__(self, config: EnvConfig, moves: torch.Tensor) -> None:
        k = int(config.far_view)
        if k < 1:
            raise ValueError(f"far_view={config.far_view!r}: FarView needs k >= 1 (0 is the paper's view)")
        self.k, self.grid = k, (config.width, config.height)
        self.m_f, self.m_e = config.m_f, config.m_e
        self.centres = moves * (k + 1)  # [8, 2]: each window's centre, less the UAV's cell
        self.size = torch.tensor(self.grid, dtype=torch.int64, device=moves.device)
        # m(U) of every (positive, negative) count pair a cell can hold, read with one gather.
        most = config.n_uavs * (config.max_steps + 1) + 1
        self.table: torch.Tensor | None = None
        self.stride = most
        if config.evidence_decay == 0 and most * most <= MAX_TABLE_ENTRIES:
            counts = torch.arange(most, device=moves.device)
            _, _, unknown = belief_masses(counts.view(-1, 1), counts.view(1, -1), config.m_f, config.m_e)
            self.table = unknown.reshape(-1).contiguous()

    def unknown_maps(self, counts: torch.Tensor, zones: torch.Tensor | None = None) -> torch.Tensor:
        """Return own m(U) maps ``[E, N, W, H]`` from each UAV's fused counts ``[E, N, 2 C]``. Cells where
        ``zones`` ``[E, C]`` is True, the known no-fly cells, hold 0."""
        positive, negative = counts[..., 0::2], counts[..., 1::2]
        if self.table is not None and not counts.is_floating_point():
            index = positive.to(torch.int32) * self.stride + negative  # < 2**22: exact in int32
            unknown = self.table.index_select(0, index.view(-1))  # a flat lookup: faster than table[index]
        else:
            unknown = belief_masses(positive, negative, self.m_f, self.m_e)[2]
        unknown = unknown.view((*counts.shape[:2], -1))
        if zones is not None:
            unknown = unknown.masked_fill(zones.unsqueeze(1), 0.0)
        return unknown.view(*counts.shape[:2], *self.grid)

    def means(self, unknown: torch.Tensor, position: torch.Tensor) -> torch.Tensor:
        """``[E, N, 8]`` window means, from own m(U) maps ``[E, N, W, H]`` and positions ``[E, N, 2]``."""
        E, N, W, H = unknown.shape
        # Summed-area table: summed[x, y] is the sum over cells [0, x] x [0, y], and a window's sum is four
        # reads of it. In float32 each mean is within about 1e-6 of the exact one.
        flat = unknown.reshape(E * N, W, H).cumsum(1).cumsum(2).view(E * N, W * H)
        centre = position.unsqueeze(2) + self.centres  # [E, N, 8, 2]
        low = torch.minimum((centre - self.k).clamp(min=0), self.size)  # the window's part on the grid
        high = torch.maximum(torch.minimum(centre + self.k + 1, self.size), low)

        def at(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
            index = ((x - 1).clamp(min=0) * H + (y - 1).clamp(min=0)).view(E * N, 8)
            return flat.gather(1, index) * ((x > 0) & (y > 0)).view(E * N, 8)

        (x0, y0), (x1, y1) = low.unbind(-1), high.unbind(-1)
        total = at(x1, y1) - at(x0, y1) - at(x1, y0) + at(x0, y0)
        return (total / (2 * self.k + 1) ** 2).view(E, N, 8)

    def observe(
        self, counts: torch.Tensor, position: torch.Tensor, zones: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Return the far view ``[E, N, 8]`` of every UAV from its fused counts, its cell and the known no-fly
        cells."""
        return self.means(self.unknown_maps(counts, zones), position)
