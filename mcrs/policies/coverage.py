"""Coverage baseline: the lawnmower's strips, with detours around the cells the reward would charge.

The plain lawnmower flies through no-fly zones (r3) because it never reads its observation. This policy
keeps the same snake path, but each UAV decides from its own observation and the zones it has seen this
episode; zones do not move, so one sighting suffices. It skips snake cells r3 would charge and follows a
shortest path around the charged cells it knows of. Among equally short moves it prefers larger m(U) (r1),
keeps off other UAVs' cells and gives way to lower-indexed UAVs (r4)."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from tensordict import TensorDictBase

from mcrs.env.config import EnvConfig
from mcrs.env.core import MOVES
from mcrs.policies.base import ACTION_MASK, OBSERVATION
from mcrs.policies.lawnmower import LawnmowerPolicy

# Per remembered no-fly zone whose r3 would charge the destination: larger than every other term
# together, so a charged cell is entered only when every allowed move is charged.
ZONE_PENALTY = 1000.0
# Per visible UAV on the destination now: second to zones. Not ``violates``: under ``near`` that would
# also push apart UAVs side by side, both ways at once, and they block each other.
UAV_PENALTY = 10.0
# Times the share of a visible lower-indexed UAV's 8 moves that would end where r4 charges with the
# destination: a 1-in-8 risk outweighs a step of PROGRESS, so the later UAV steps aside. Only one of two
# UAVs gives way (symmetric avoidance left pairs blocking each other: docs/PERFORMANCE.md, "Figures
# behind constants").
CONTACT_PENALTY = 16.0
# Per move of path length from the destination to the waypoint: the lawnmower's pull.
PROGRESS = 1.0
# Per unit of m(U) at the destination: < PROGRESS, so it chooses among equally short moves (a detour
# around a zone has several) without leaving the path. Weights that let it leave the path for unknown
# cells scored lower (docs/PERFORMANCE.md, "Figures behind constants").
GAIN = 0.9
TIE_TOLERANCE = 1e-6


class CoveragePolicy(LawnmowerPolicy):
    """The lawnmower's snake followed around known charged cells, remembering seen zones per env and UAV.

    A move scores ``- PROGRESS * (path length to the waypoint) + GAIN * m(U)(destination) - ZONE_PENALTY *
    (remembered zones charging it) - UAV_PENALTY * (visible UAVs on it) - CONTACT_PENALTY * (share of each
    visible lower-indexed UAV's moves ending where r4 charges)``, judged by :meth:`EnvConfig.violates`.
    Path lengths are 8-connected and avoid known charged cells. The waypoint pointer skips charged snake
    cells and the UAV's own cell, and gives up a waypoint no known path reaches. Ties use the seeded
    generator; memory and pointer restart where ``step_count == 0``."""

    def __init__(self, config: EnvConfig, seed: int = 0) -> None:
        if config.relative_order != "index":
            raise ValueError(
                f"policy coverage: env.relative_order={config.relative_order} is not supported: it remembers "
                "zones by their observation slot and gives way to UAVs by index; use env.relative_order=index"
            )
        super().__init__(config, seed)
        dev = torch.device(config.device)
        n = config.n_uavs
        self.moves = torch.tensor(MOVES, dtype=torch.int64, device=dev)
        self.ahead = torch.arange(int(self.cycle.max()), device=dev)  # pointer offsets scanned per step
        self.kernel = charged_offsets(config).to(dev)  # [1, 1, 2r+1, 2r+1]
        self.grid_max = torch.tensor([config.width - 1, config.height - 1], device=dev)
        # earlier[i, k]: observation slot k of UAV i (the other UAVs in index order) is a UAV j < i.
        self.earlier = torch.arange(n - 1, device=dev).view(1, -1) < torch.arange(n, device=dev).view(-1, 1)
        self.zone_cell: torch.Tensor | None = None  # [E, N, Z, 2] last seen cell of each zone
        self.zone_known: torch.Tensor | None = None  # [E, N, Z] zone seen in this episode

    # ------------------------------------------------------------------ memory
    def _remember(self, observation: torch.Tensor, position: torch.Tensor, new_episode: torch.Tensor) -> None:
        """Store the absolute cells of the zones in sight; forget the others where an episode starts."""
        offset, visible = self.layout.relative_cells(self.layout.no_fly_features(observation))
        cell = position.unsqueeze(-2) + offset  # [E, N, Z, 2]
        fresh = self.zone_cell is None or self.zone_cell.shape != cell.shape
        if fresh or self.zone_cell.device != cell.device:
            self.zone_cell, self.zone_known = cell, visible
            return
        self.zone_cell = torch.where(visible.unsqueeze(-1), cell, self.zone_cell)
        self.zone_known = (self.zone_known & ~new_episode.unsqueeze(-1)) | visible

    def _charged_map(self) -> torch.Tensor:
        """Return ``[E, N, W * H]`` bool, x-major: the cells where r3 would charge, as far as each UAV knows."""
        c = self.config
        E, N, _ = self.zone_known.shape
        zones = torch.zeros(E, N, c.n_cells, device=self.zone_known.device)
        index = (self.zone_cell[..., 0] * c.height + self.zone_cell[..., 1]).clamp(0, c.n_cells - 1)
        zones.scatter_add_(-1, index, self.zone_known.to(zones.dtype))
        pad = self.kernel.shape[-1] // 2
        spread = F.conv2d(zones.view(E * N, 1, c.width, c.height), self.kernel, padding=pad)
        return (spread > 0.5).view(E, N, c.n_cells)

    def _zone_charges(self, cells: torch.Tensor) -> torch.Tensor:
        """Count the remembered zones whose r3 would charge a UAV on each of ``cells [E, N, K, 2]``."""
        squared = (cells.unsqueeze(-2) - self.zone_cell.unsqueeze(-3)).pow(2).sum(-1).to(torch.float32)
        charged = self.config.violates(squared, self.config.no_fly_safety) & self.zone_known.unsqueeze(-2)
        return charged.sum(-1)

    # ------------------------------------------------------------------ path
    def _waypoints(self, pointer: torch.Tensor) -> torch.Tensor:
        """Return the snake cells ``[E, N, K, 2]`` at pointers ``[E, N, K]``."""
        p = self.path_length.unsqueeze(-1)
        k = torch.where(pointer < p, pointer, 2 * p - 2 - pointer)
        column, row = k // self.config.height, k % self.config.height
        y = torch.where(column % 2 == 0, row, self.config.height - 1 - row)
        return torch.stack([self.strip_first.unsqueeze(-1) + column, y], dim=-1)

    def _advance(self, position: torch.Tensor, charged: torch.Tensor) -> None:
        """Move each pointer to the first snake cell from it that is neither charged nor reached."""
        index = (self.pointer.unsqueeze(-1) + self.ahead) % self.cycle.unsqueeze(-1)  # [E, N, C]
        cells = self._waypoints(index)
        flat = cells[..., 0] * self.config.height + cells[..., 1]
        skip = charged.gather(-1, flat) | (cells == position.unsqueeze(-2)).all(-1)
        first = (~skip).to(torch.int64).argmax(-1, keepdim=True)
        self.pointer = torch.where(skip.all(-1), self.pointer, index.gather(-1, first).squeeze(-1))

    def _path_lengths(self, charged: torch.Tensor, waypoint: torch.Tensor) -> torch.Tensor:
        """Return ``[E, N, W * H]`` moves from each cell to the waypoint through uncharged cells (inf without
        a path), by batched breadth-first search."""
        c = self.config
        E, N, _ = charged.shape
        blocked = charged.view(E * N, 1, c.width, c.height)
        goal = (waypoint[..., 0] * c.height + waypoint[..., 1]).unsqueeze(-1)
        distance = torch.full((E, N, c.n_cells), math.inf, device=charged.device).scatter_(-1, goal, 0.0)
        distance = distance.view(E * N, 1, c.width, c.height)
        for _ in range(c.n_cells):
            relaxed = torch.minimum(distance, 1.0 - F.max_pool2d(-distance, 3, stride=1, padding=1))
            relaxed = relaxed.masked_fill(blocked, math.inf)
            if torch.equal(relaxed, distance):
                break
            distance = relaxed
        return distance.view(E, N, c.n_cells)

    # ------------------------------------------------------------------ moves
    def _uav_terms(self, observation: torch.Tensor, moves: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Return ``[E, N, 8]`` visible UAVs on each destination, and the summed share of lower-indexed UAVs'
        moves r4 would charge there."""
        offset, visible = self.layout.relative_cells(self.layout.uav_features(observation))  # [E, N, U, 2]
        on = (offset.unsqueeze(-3) == moves.unsqueeze(-2)).all(-1) & visible.unsqueeze(-2)  # [E, N, 8, U]
        reach = offset.unsqueeze(-2) + self.moves  # [E, N, U, 8', 2]
        gap = reach.unsqueeze(-4) - moves.view(*moves.shape[:-1], 1, 1, 2)  # [E, N, 8, U, 8', 2]
        close = self.config.violates(gap.pow(2).sum(-1).to(torch.float32), self.config.uav_safety)
        contact = close.to(torch.float32).mean(-1) * (visible & self.earlier).unsqueeze(-2)
        return on.sum(-1), contact.sum(-1)

    def scores(
        self, observation: torch.Tensor, position: torch.Tensor, mask: torch.Tensor, charged: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Return ``[E, N, 8]`` move scores (-inf when masked), and ``[E, N]`` where no allowed move has a
        known path."""
        c = self.config
        moves = self.moves.expand(*position.shape[:-1], 8, 2)
        destination = position.unsqueeze(-2) + moves
        clamped = torch.minimum(destination.clamp(min=0), self.grid_max)
        waypoint = self.waypoint(self.pointer)
        path = self._path_lengths(charged, waypoint)
        path = path.gather(-1, clamped[..., 0] * c.height + clamped[..., 1])
        lost = ~(path.isfinite() & mask).any(-1)
        # Without a known path, head straight for the waypoint, behind every move that has one.
        straight = (waypoint.unsqueeze(-2) - destination).abs().amax(-1).to(torch.float32) + c.n_cells
        distance = torch.where(path.isfinite(), path, straight)
        score = GAIN * self.layout.unknown_by_action(observation) - PROGRESS * distance
        score = score - ZONE_PENALTY * self._zone_charges(destination)
        if self.layout.n_others:
            on, contact = self._uav_terms(observation, moves)
            score = score - UAV_PENALTY * on - CONTACT_PENALTY * contact
        return score.masked_fill(~mask, float("-inf")), lost

    def act(self, tensordict: TensorDictBase) -> torch.Tensor:
        observation = tensordict.get(OBSERVATION)
        mask = tensordict.get(ACTION_MASK)
        position = self.layout.cell(observation)  # [E, N, 2]
        new_episode = (tensordict.get("step_count").reshape(-1) == 0).view(-1, 1)
        self._restart_pointer(position, new_episode)
        self._remember(observation, position, new_episode)
        charged = self._charged_map()
        self._advance(position, charged)
        score, lost = self.scores(observation, position, mask, charged)
        # A waypoint that no known path reaches is given up: the next step aims further along the snake.
        self.pointer = torch.where(lost, (self.pointer + 1) % self.cycle, self.pointer)
        best = score.amax(-1, keepdim=True)
        return self._uniform_among((score >= best - TIE_TOLERANCE) & mask)


def charged_offsets(config: EnvConfig) -> torch.Tensor:
    """Return a ``[1, 1, 2r+1, 2r+1]`` kernel that is 1 at each offset from a zone where r3 charges, to spread
    zone cells into charged cells."""
    d1 = config.no_fly_safety
    radius = max(config.width, config.height) - 1
    if math.isfinite(d1):
        radius = min(radius, math.ceil(d1))
    span = torch.arange(-radius, radius + 1, dtype=torch.float32)
    squared = span.view(-1, 1).pow(2) + span.view(1, -1).pow(2)
    return config.violates(squared, d1).to(torch.float32).view(1, 1, 2 * radius + 1, 2 * radius + 1)
