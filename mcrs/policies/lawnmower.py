"""Lawnmower (boustrophedon) baseline: the classic coverage pattern, blind to beliefs.

The x range is split into one strip of columns per UAV. Each UAV snakes through every cell of its strip,
then back along the same path, so it keeps covering its strip for any T."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from mcrs.env.config import EnvConfig
from mcrs.env.core import MOVES
from mcrs.policies.base import ACTION_MASK, OBSERVATION, Policy


def strip_bounds(config: EnvConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Return the first column ``[N]`` and width ``[N]`` of each UAV's strip, at least one column each."""
    n, width = config.n_uavs, config.width
    edges = torch.arange(n + 1) * width // n
    first = edges[:-1].clamp(max=width - 1)
    return first, (edges[1:] - edges[:-1]).clamp(min=1)


class LawnmowerPolicy(Policy):
    """Each UAV follows the snake path of its own strip, with a path pointer per env and UAV.

    The pointer runs over a cycle of length ``2P - 2`` for ``P`` cells: forwards while ``s < P``, then
    back. At an episode's start each UAV aims at the nearer end of its snake. Each step it takes the move
    whose (dx, dy) is the sign of (waypoint - position), which never leaves the grid. Where a shield masks
    that move, it takes the allowed move ending nearest the waypoint, the lowest action among equals."""

    def __init__(self, config: EnvConfig, seed: int = 0) -> None:
        super().__init__(config, seed)
        first, width = strip_bounds(config)
        dev = torch.device(config.device)
        self.strip_first = first.to(dev)
        self.strip_width = width.to(dev)
        self.path_length = (width * config.height).to(dev)  # P per UAV
        self.cycle = (2 * self.path_length - 2).clamp(min=1)
        # MOVE_LOOKUP[dx + 1, dy + 1] = action with that (dx, dy); -1 for (0, 0), which has no action.
        lookup = torch.full((3, 3), -1, dtype=torch.int64)
        for action, (dx, dy) in enumerate(MOVES):
            lookup[dx + 1, dy + 1] = action
        self.move_lookup = lookup.to(dev)
        self.moves = torch.tensor(MOVES, dtype=torch.int64, device=dev)
        self.pointer: torch.Tensor | None = None  # [E, N] position in the ping-pong cycle

    def waypoint(self, pointer: torch.Tensor) -> torch.Tensor:
        """Return the snake cell ``[E, N, 2]`` at each pointer."""
        p = self.path_length
        k = torch.where(pointer < p, pointer, 2 * p - 2 - pointer)  # index along the snake
        column, row = k // self.config.height, k % self.config.height
        y = torch.where(column % 2 == 0, row, self.config.height - 1 - row)
        return torch.stack([self.strip_first + column, y], dim=-1)

    def _start_pointer(self, position: torch.Tensor) -> torch.Tensor:
        """Return the pointer to the nearer end, in moves, of each UAV's snake."""
        start = torch.zeros_like(position[..., 0])
        end = (self.path_length - 1).expand_as(start)
        moves_to = [(self.waypoint(s) - position).abs().amax(-1) for s in (start, end)]
        return torch.where(moves_to[1] < moves_to[0], end, start)

    def _restart_pointer(self, position: torch.Tensor, new_episode: torch.Tensor) -> None:
        """Aim each UAV of a new episode at the nearer end of its snake; a batch of another shape or device
        starts afresh."""
        start = self._start_pointer(position)
        if self.pointer is None or self.pointer.shape != start.shape or self.pointer.device != start.device:
            self.pointer = start
        else:
            self.pointer = torch.where(new_episode, start, self.pointer)

    def act(self, tensordict: TensorDictBase) -> torch.Tensor:
        obs = tensordict.get(OBSERVATION)
        mask = tensordict.get(ACTION_MASK)
        position = self.layout.cell(obs)  # [E, N, 2]
        new_episode = (tensordict.get("step_count").reshape(-1) == 0).view(-1, 1)
        self._restart_pointer(position, new_episode)
        arrived = (self.waypoint(self.pointer) == position).all(-1)
        self.pointer = torch.where(arrived, (self.pointer + 1) % self.cycle, self.pointer)
        waypoint = self.waypoint(self.pointer)
        step = (waypoint - position).sign()
        action = self.move_lookup[step[..., 0] + 1, step[..., 1] + 1]
        # -1 only where a one-cell strip leaves the UAV on its waypoint.
        allowed = (action >= 0) & mask.gather(-1, action.clamp(min=0).unsqueeze(-1)).squeeze(-1)
        destination = position.unsqueeze(-2) + self.moves  # [E, N, 8, 2]
        distance = (waypoint.unsqueeze(-2) - destination).pow(2).sum(-1).to(torch.float32)
        nearest = distance.masked_fill(~mask, float("inf")).argmin(-1)
        return torch.where(allowed, action, nearest)
