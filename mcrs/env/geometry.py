"""Offsets and distances between UAVs and to no-fly zones, computed once per step for the links, penalties and
observations."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class Geometry:
    """Offsets and squared distances from each UAV to the others and to the no-fly zones. The x and y planes
    are separate because elementwise ops over a trailing dimension of 2 are several times slower on CPU.
    Squared distances of integer cells are exact, so every range test uses them."""

    uav_dx: torch.Tensor  # [E, N, N] float32: x_j - x_i
    uav_dy: torch.Tensor  # [E, N, N]
    uav_squared: torch.Tensor  # [E, N, N]
    no_fly_dx: torch.Tensor  # [E, N, Z]: x of zone k - x_i
    no_fly_dy: torch.Tensor  # [E, N, Z]
    no_fly_squared: torch.Tensor  # [E, N, Z]

    @classmethod
    def of(cls, uav_pos: torch.Tensor, no_fly_pos: torch.Tensor) -> Geometry:
        """The geometry of UAVs at ``uav_pos [E, N, 2]`` and zones at ``no_fly_pos [E, Z, 2]`` (cells)."""
        # float32 holds these small integer offsets and their squares exactly, and is cheaper than int64.
        x, y = uav_pos.to(torch.float32).unbind(-1)
        zx, zy = no_fly_pos.to(torch.float32).unbind(-1)
        uav_dx, uav_dy = x.unsqueeze(1) - x.unsqueeze(2), y.unsqueeze(1) - y.unsqueeze(2)
        no_fly_dx, no_fly_dy = zx.unsqueeze(1) - x.unsqueeze(2), zy.unsqueeze(1) - y.unsqueeze(2)
        return cls(
            uav_dx,
            uav_dy,
            uav_dx * uav_dx + uav_dy * uav_dy,
            no_fly_dx,
            no_fly_dy,
            no_fly_dx * no_fly_dx + no_fly_dy * no_fly_dy,
        )
