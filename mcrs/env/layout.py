"""Named slices of the flat observation and state vectors, so that no consumer hard-codes offsets.

Policies, renderers, the episodic memory's codec, the embeddings and the analysis read the observation
(paper eqs. 18-21) and the global state (eq. 22) through :class:`ObservationLayout`, :class:`StateLayout`
and :class:`MapImage`."""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise
from typing import ClassVar

import torch

from mcrs.env.config import N_FAR_VIEW, EnvConfig
from mcrs.env.core import MOVES, SURROUNDING

# ACTION_TO_SURROUNDING[a] is the index in the observation's 8-cell block (order ``SURROUNDING``) of the
# cell that action ``a`` (order ``MOVES``) moves to: the two orders differ.
ACTION_TO_SURROUNDING: tuple[int, ...] = tuple(SURROUNDING.index(move) for move in MOVES)


@dataclass(frozen=True)
class ObservationLayout:
    """Where each feature group of one UAV's observation lies (length ``18 + 3(N-1) + 3 N_Z``, plus 8 with the
    far view)."""

    position: slice  # x / (L1 - 1), y / (L2 - 1)
    # Own fused m(U) at the 8 SURROUNDING cells, 0 where the UAV cannot move (off the grid, no-fly).
    unknown_around: slice
    full_around: slice  # own fused m(F) at the same cells
    uavs: slice  # (d, dx, dy) / R_sight for every other UAV in index order, zeros beyond sight
    no_fly: slice  # (d, dx, dy) / R_sight for every no-fly zone, zeros beyond sight
    far_view: slice  # 8 window means of own m(U) in action order when env.far_view > 0, else empty
    obs_dim: int
    n_others: int  # N - 1
    n_no_fly: int
    sight_range: float
    grid_max: tuple[int, int]  # (L1 - 1, L2 - 1): the position normalisation

    @classmethod
    def from_config(cls, cfg: EnvConfig) -> ObservationLayout:
        n_others, n_no_fly = cfg.n_uavs - 1, cfg.n_no_fly
        bounds = [2, 8, 8, 3 * n_others, 3 * n_no_fly, N_FAR_VIEW if cfg.far_view > 0 else 0]
        starts = [sum(bounds[:k]) for k in range(len(bounds) + 1)]
        position, unknown, full, uavs, no_fly, far_view = (slice(a, b) for a, b in pairwise(starts))
        if starts[-1] != cfg.obs_dim:  # a guard: the config's formula and this layout must agree
            raise AssertionError(f"observation layout length {starts[-1]} != config obs_dim {cfg.obs_dim}")
        return cls(
            position=position,
            unknown_around=unknown,
            full_around=full,
            uavs=uavs,
            no_fly=no_fly,
            far_view=far_view,
            obs_dim=cfg.obs_dim,
            n_others=n_others,
            n_no_fly=n_no_fly,
            sight_range=float(cfg.sight_range),
            grid_max=(max(cfg.width - 1, 1), max(cfg.height - 1, 1)),
        )

    # ------------------------------------------------------------------ readers, all batched over [...]
    def cell(self, obs: torch.Tensor) -> torch.Tensor:
        """``[..., 2]`` int64: the UAV's own cell (x, y), undoing the normalisation."""
        scale = torch.tensor(self.grid_max, dtype=obs.dtype, device=obs.device)
        return (obs[..., self.position] * scale).round().to(torch.int64)

    def unknown_by_action(self, obs: torch.Tensor) -> torch.Tensor:
        """``[..., 8]``: m(U) of the cell each action moves to, in action order (``MOVES``)."""
        return obs[..., self.unknown_around][..., list(ACTION_TO_SURROUNDING)]

    def full_by_action(self, obs: torch.Tensor) -> torch.Tensor:
        """``[..., 8]``: m(F) of the cell each action moves to, in action order (``MOVES``)."""
        return obs[..., self.full_around][..., list(ACTION_TO_SURROUNDING)]

    def uav_features(self, obs: torch.Tensor) -> torch.Tensor:
        """``[..., N-1, 3]``: normalised (d, dx, dy) to each other UAV."""
        return obs[..., self.uavs].unflatten(-1, (self.n_others, 3))

    def no_fly_features(self, obs: torch.Tensor) -> torch.Tensor:
        """``[..., N_Z, 3]``: normalised (d, dx, dy) to each no-fly zone."""
        return obs[..., self.no_fly].unflatten(-1, (self.n_no_fly, 3))

    def far_unknown_by_action(self, obs: torch.Tensor) -> torch.Tensor:
        """``[..., 8]``: mean own m(U) of the far window in each move's direction (``far_view`` > 0 only)."""
        if self.far_view.stop == self.far_view.start:
            raise ValueError(
                "this observation has no far view: the env was made with far_view=0 (the paper's)"
            )
        return obs[..., self.far_view]

    def relative_cells(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Return integer offsets ``[..., K, 2]`` from ``uav_features``/``no_fly_features``, and visibility
        ``[..., K]``. An entity is visible when its distance is > 0. An entity on the UAV's own cell also
        reads (0, 0, 0), so the paper's layout cannot tell it from an invisible one."""
        offset = (features[..., 1:] * self.sight_range).round().to(torch.int64)
        return offset, features[..., 0] > 0


@dataclass(frozen=True)
class MapImage:
    """The head of the global state: the maps m(U) then m(F), each x-major (index ``x * L2 + y``). As an image
    ``[2, L1, L2]`` (the env's ``state_map`` key) it is what the CNN embedding convolves."""

    width: int
    height: int
    channels: ClassVar[int] = 2  # m(U), m(F)

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(2, L1, L2)``."""
        return (self.channels, self.width, self.height)

    @property
    def dim(self) -> int:
        """The number of state values the maps take, ``2 L1 L2``."""
        return self.channels * self.width * self.height

    def image(self, state: torch.Tensor) -> torch.Tensor:
        """``[..., 2, L1, L2]``: a view of the maps at the head of ``state [..., D]``."""
        return state[..., : self.dim].unflatten(-1, self.shape)

    def rest(self, state: torch.Tensor) -> torch.Tensor:
        """``[..., D - 2 L1 L2]``: the scaled positions after the maps."""
        return state[..., self.dim :]


@dataclass(frozen=True)
class StateLayout:
    """Where each part of the global state (paper eq. 22, length ``2 L1 L2 + 2N + 2N_Z + 2N_T``) lies."""

    unknown: slice  # global m(U), x-major
    full: slice  # global m(F), x-major
    uav_position: slice
    no_fly_position: slice
    target_position: slice
    state_dim: int
    width: int
    height: int

    @classmethod
    def from_config(cls, cfg: EnvConfig) -> StateLayout:
        bounds = [cfg.n_cells, cfg.n_cells, 2 * cfg.n_uavs, 2 * cfg.n_no_fly, 2 * cfg.n_targets]
        starts = [sum(bounds[:k]) for k in range(len(bounds) + 1)]
        unknown, full, uavs, no_fly, targets = (slice(a, b) for a, b in pairwise(starts))
        if starts[-1] != cfg.state_dim:
            raise AssertionError(f"state layout length {starts[-1]} != config state_dim {cfg.state_dim}")
        return cls(unknown, full, uavs, no_fly, targets, cfg.state_dim, cfg.width, cfg.height)

    @property
    def map_image(self) -> MapImage:
        """The maps at the head of the state (``unknown`` then ``full``) as an image."""
        return MapImage(self.width, self.height)

    @property
    def map_dim(self) -> int:
        """``2 L1 L2``: the maps come first; the positions start here."""
        return self.full.stop

    @property
    def positions(self) -> slice:
        """Every position part as (x, y) pairs: UAVs, then no-fly zones, then targets."""
        return slice(self.uav_position.start, self.target_position.stop)

    @property
    def n_positions(self) -> int:
        """``N + N_Z + N_T``: the (x, y) pairs in :attr:`positions`."""
        return (self.positions.stop - self.positions.start) // 2

    @property
    def pos_scale(self) -> tuple[int, int]:
        """``(L1 - 1, L2 - 1)`` clamped to >= 1: a position value is ``cell / pos_scale`` in float32."""
        return (max(self.width - 1, 1), max(self.height - 1, 1))

    def cells(self, state: torch.Tensor, part: slice) -> torch.Tensor:
        """``[..., K, 2]`` int64 cells (x, y) of a position part (``uav_position`` etc.) of ``state``."""
        scale = torch.tensor(self.pos_scale, dtype=state.dtype, device=state.device)
        return (state[..., part].unflatten(-1, (-1, 2)) * scale).round().to(torch.int64)

    def maps(self, state: torch.Tensor) -> torch.Tensor:
        """``[..., 2, L1, L2]``: global m(U), m(F) as images (the same as the ``state_map`` key)."""
        return self.map_image.image(state)
