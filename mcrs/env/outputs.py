"""What :class:`~mcrs.env.core.MCRSCore` returns after a reset or a step: the :class:`StepResult`.

It holds each UAV's observation, the global state, the action mask, the running metrics and, with
``expose_beliefs``, the belief maps. :class:`CoreOutputs` is a base class of ``MCRSCore`` that only reads
the episode state the core advances."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from mcrs.env.belief import belief_masses
from mcrs.env.fusion import neighbours_within
from mcrs.env.geometry import Geometry

__all__ = ["CoreOutputs", "StepResult"]


@dataclass
class StepResult:
    """What one reset or step produces, every entry batched over environments."""

    observation: torch.Tensor  # [E, N, obs_dim]
    action_mask: torch.Tensor  # [E, N, 8] bool
    state: torch.Tensor  # [E, state_dim]
    state_map: torch.Tensor  # [E, 2, width, height]: global m(U), m(F) as an image
    # [E, cells, 2] global (positive, negative) counts per cell: int, or float32 when they decay
    state_counts: torch.Tensor
    position: torch.Tensor  # [E, N, 2] int64
    reading: torch.Tensor  # [E, N] bool: True when the UAV read "F" this step
    reward: torch.Tensor  # [E] float32 team reward (zero after a reset)
    reward_terms: torch.Tensor  # [E, 4]: r1 uncertainty, r2 discovery, r3 no-fly, r4 collision
    step_count: torch.Tensor  # [E] int64: steps taken in the episode
    truncated: torch.Tensor  # [E] bool: the time limit T is reached
    metrics: dict[str, torch.Tensor]  # each [E] float32, running values of the episode
    belief_map: torch.Tensor | None = None  # [E, N, 2, width, height] each UAV's fused m(U), m(F)
    neighbours: torch.Tensor | None = None  # [E, N, N] bool communication graph of this step


def nearest_first(relative: torch.Tensor, squared: torch.Tensor, n_others: int) -> torch.Tensor:
    """Sort the other UAVs' slots (the first ``n_others``) and the zones' slots of ``relative`` ``[E, N, K,
    3]``. Each group is sorted by ``squared`` distance ``[E, N, K]``, inf beyond sight, ties in index
    order."""
    order = torch.cat(
        [
            squared[..., :n_others].argsort(dim=-1, stable=True),
            squared[..., n_others:].argsort(dim=-1, stable=True) + n_others,
        ],
        dim=-1,
    )
    return relative.gather(2, order.unsqueeze(-1).expand_as(relative))


class CoreOutputs:
    """The output half of :class:`~mcrs.env.core.MCRSCore`: the observation, the result and the belief maps."""

    def _observation(self, geometry: Geometry, cell: torch.Tensor) -> torch.Tensor:
        c = self.config
        E, N = self.num_envs, self.n_uavs
        around = self.counts.gather(2, self._around_counts[cell]).view(E, N, 2, 8)
        if self.decay is not None:
            around = self.decay.now(around, self.step_count)
        movable = self._around_on_grid[cell]
        if self.hide_zones:  # a no-fly direction shows 0, as off the grid (config.NO_FLY_VIEWS)
            zone = self.is_no_fly.gather(1, self._around_cell[cell].view(E, N * 8)).view(E, N, 8)
            movable = movable.masked_fill(zone, 0.0)
        _, full, unknown = belief_masses(around[:, :, 0], around[:, :, 1], c.m_f, c.m_e)

        # Relative positions: every other UAV in index order, then every no-fly zone ([E, N, K]).
        def objects(uav_plane: torch.Tensor, no_fly_plane: torch.Tensor) -> torch.Tensor:
            others = uav_plane.view(E, N * N).index_select(1, self._other_pairs).view(E, N, N - 1)
            return torch.cat([others, no_fly_plane], dim=2)

        squared = objects(geometry.uav_squared, geometry.no_fly_squared)
        in_sight = squared <= c.sight_range**2
        scale = in_sight.to(torch.float32) / c.sight_range  # zero beyond sight
        relative = torch.stack(
            [
                squared.sqrt() * scale,
                objects(geometry.uav_dx, geometry.no_fly_dx) * scale,
                objects(geometry.uav_dy, geometry.no_fly_dy) * scale,
            ],
            dim=-1,
        )  # (d, dx, dy) / R_sight
        if c.relative_order == "nearest":
            relative = nearest_first(relative, squared.masked_fill(~in_sight, float("inf")), N - 1)
        parts = [
            self.uav_pos.to(torch.float32) / self._pos_scale,
            unknown * movable,
            full * movable,
            relative.view(E, N, -1),
        ]
        if self.far_view is not None:  # 8 window means of own m(U) (mcrs/env/far_view.py)
            zones = self.is_no_fly if self.known_zones else None
            parts.append(self.far_view.observe(self.counts_now(), self.uav_pos, zones))
        return torch.cat(parts, dim=-1)

    def _result(
        self, terms: torch.Tensor, geometry: Geometry | None = None, neighbours: torch.Tensor | None = None
    ) -> StepResult:
        c = self.config
        E = self.num_envs
        geometry = geometry if geometry is not None else self._geometry()
        if neighbours is None:
            neighbours = neighbours_within(geometry.uav_squared, c.comm_range)
        cell = self._uav_cells()
        self._mask = self._action_mask(cell, geometry)
        positions = [self.uav_pos, self.no_fly_pos, self.target_pos]
        state = torch.cat(
            [self.global_belief.view(E, -1)]
            + [(p.to(torch.float32) / self._pos_scale).reshape(E, -1) for p in positions],
            dim=-1,
        )
        metrics = {
            "episode_reward": self.episode_reward.clone(),
            "uncertainty": self.total_uncertainty.clone(),
            "targets_found": self.targets_found.clone(),
            "false_discoveries": self.false_discoveries.clone(),
            "collisions": self.collisions.clone(),
            "no_fly_violations": self.no_fly_violations.clone(),
            "coverage": self.cells_sensed / self.n_cells,
        }
        result = StepResult(
            observation=self._observation(geometry, cell),
            action_mask=self._mask.clone(),
            state=state,
            state_map=state[:, : 2 * self.n_cells].view(E, 2, c.width, c.height),  # a view, no copy
            state_counts=self.global_counts.view(E, self.n_cells, 2).clone(),
            position=self.uav_pos.clone(),
            reading=self.reading.clone(),
            reward=terms.sum(-1),
            reward_terms=terms,
            step_count=self.step_count.clone(),
            truncated=self.step_count >= c.max_steps,
            metrics=metrics,
        )
        if c.expose_beliefs:
            result.belief_map = self.belief_maps()
            result.neighbours = neighbours
        return result

    def belief_maps(self) -> torch.Tensor:
        """``[E, N, 2, width, height]``: each UAV's own fused m(U) and m(F) maps."""
        c = self.config
        counts = self.counts_now()
        _, full, unknown = belief_masses(counts[..., 0::2], counts[..., 1::2], c.m_f, c.m_e)
        if self.known_zones:
            zone = self.is_no_fly.unsqueeze(1)
            unknown, full = unknown.masked_fill(zone, 0.0), full.masked_fill(zone, 0.0)
        return torch.stack([unknown, full], dim=2).view(self.num_envs, self.n_uavs, 2, c.width, c.height)
