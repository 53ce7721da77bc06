"""Moving targets (``target_motion=random_walk``), a variant beyond the paper's static targets."""

from __future__ import annotations

import torch

from mcrs.env.config import EnvConfig


class TargetWalk:
    """Each step, each target tries with ``target_move_prob`` one of the 8 moves of eq. 1, uniformly.

    The move happens when the new cell is on the grid, not a no-fly cell and held by no target at the start
    of the step; when several targets choose one free cell, the lowest-indexed one moves. The draws come
    from the env's generator before the readings: ``rand [E, K]``, then ``randint(0, 8) [E, K]``."""

    def __init__(self, config: EnvConfig, moves: torch.Tensor, device: torch.device) -> None:
        E = config.num_envs
        self.config, self.moves = config, moves
        self.grid_max = torch.tensor([config.width - 1, config.height - 1], dtype=torch.int64, device=device)
        self.is_no_fly = torch.zeros(E, config.n_cells, dtype=torch.bool, device=device)

    def tensors(self) -> list[torch.Tensor]:
        return [self.is_no_fly]

    def start(self, envs: torch.Tensor, no_fly_cells: torch.Tensor) -> None:
        """Start new episodes in ``envs`` with no-fly zones on the flat cells ``no_fly_cells [M, Z]``."""
        is_no_fly = torch.zeros(envs.numel(), self.config.n_cells, dtype=torch.bool, device=envs.device)
        self.is_no_fly[envs] = is_no_fly.scatter_(1, no_fly_cells, True)

    def step(
        self, position: torch.Tensor, is_target: torch.Tensor, generator: torch.Generator
    ) -> torch.Tensor:
        """Return the targets' new cells ``(x, y)`` ``[E, K, 2]``; ``is_target [E, C]`` is updated in place."""
        c, dev = self.config, position.device
        shape = position.shape[:2]
        tries = torch.rand(shape, generator=generator, device=dev) < c.target_move_prob
        move = torch.randint(0, self.moves.shape[0], shape, generator=generator, device=dev)
        dest = position + self.moves[move]
        on_grid = ((dest >= 0) & (dest <= self.grid_max)).all(-1)
        old_cell = position[..., 0] * c.height + position[..., 1]
        dest_cell = torch.where(on_grid, dest[..., 0] * c.height + dest[..., 1], old_cell)
        free = ~(self.is_no_fly.gather(1, dest_cell) | is_target.gather(1, dest_cell))
        candidate = tries & on_grid & free
        # Of the candidates choosing one cell of one env, the lowest index moves. Candidates are few
        # (about K * target_move_prob per env), so this works on them alone, not on [E, K, K] pairs.
        env, index = candidate.nonzero().unbind(-1)
        chosen, slot = torch.unique(env * c.n_cells + dest_cell[env, index], return_inverse=True)
        winner = torch.full_like(chosen, position.shape[1]).scatter_reduce_(0, slot, index, "amin")
        moves = torch.zeros_like(candidate)
        moves[env, index] = index == winner[slot]
        is_target.scatter_(1, old_cell, False)
        is_target.scatter_(1, torch.where(moves, dest_cell, old_cell), True)
        return torch.where(moves.unsqueeze(-1), dest, position)
