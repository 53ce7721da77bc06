"""Checks of what users hand the core: actions and scripted scenes, refused with one clear message."""

from __future__ import annotations

import torch

from mcrs.env.config import EnvConfig


def check_action(
    action: torch.Tensor, config: EnvConfig, mask: torch.Tensor, uav_pos: torch.Tensor
) -> torch.Tensor:
    """Return ``action`` as int64 ``[E, N]`` on the mask's device, or raise an error naming the env, UAV and
    allowed moves. Masked moves are refused too unless ``invalid_action=clip``."""
    num_envs, n_uavs, n_actions = mask.shape
    if not isinstance(action, torch.Tensor):
        raise TypeError(
            f"action must be a torch.Tensor of shape {[num_envs, n_uavs]}, got {type(action).__name__}"
        )
    if action.dtype.is_floating_point or action.dtype.is_complex or action.dtype == torch.bool:
        raise TypeError(f"action must have an integer dtype (0..{n_actions - 1}), got {action.dtype}")
    if action.shape != (num_envs, n_uavs):
        if action.numel() == num_envs * n_uavs and action.shape[:1] == (num_envs,):
            action = action.reshape(num_envs, n_uavs)  # e.g. [E, N, 1]
        else:
            raise ValueError(
                f"action must have shape [num_envs, n_uavs] = {[num_envs, n_uavs]}, got {list(action.shape)}"
            )
    action = action.to(device=mask.device, dtype=torch.int64)
    bad = (action < 0) | (action >= n_actions)
    if bad.any():
        env, uav = bad.nonzero()[0].tolist()
        raise ValueError(
            f"action[{env}, {uav}] = {action[env, uav].item()} is out of range: allowed 0..{n_actions - 1}"
        )
    if config.invalid_action == "raise":
        allowed = mask.gather(-1, action.unsqueeze(-1)).squeeze(-1)
        if not allowed.all():
            env, uav = (~allowed).nonzero()[0].tolist()
            raise ValueError(
                f"action[{env}, {uav}] = {action[env, uav].item()} is masked: it would leave the grid "
                f"{'or enter d1 of a no-fly zone (no_fly_shield) ' if config.no_fly_shield else ''}"
                f"{'or may meet a lower-indexed UAV within d2 (uav_shield) ' if config.uav_shield else ''}from "
                f"{uav_pos[env, uav].tolist()}; allowed here: "
                f"{mask[env, uav].nonzero().squeeze(-1).tolist()} "
                "(set invalid_action=clip to clip such moves instead)"
            )
    return action


def scene_cells(
    config: EnvConfig,
    num_envs: int,
    device: torch.device,
    uav_positions: torch.Tensor,
    no_fly_positions: torch.Tensor,
    target_positions: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Flat cells (UAV starts, no-fly zones, targets) of a scripted scene, checked against the reset rules."""
    grid_max = torch.tensor([config.width - 1, config.height - 1], dtype=torch.int64, device=device)
    c, E = config, num_envs
    cells = []
    for name, value, count in (
        ("uav_positions", uav_positions, c.n_uavs),
        ("no_fly_positions", no_fly_positions, c.n_no_fly),
        ("target_positions", target_positions, c.n_targets),
    ):
        value = torch.as_tensor(value, dtype=torch.int64, device=device)
        value = value.expand(E, *value.shape) if value.dim() == 2 else value
        if value.shape != (E, count, 2):
            raise ValueError(f"{name} must have shape {[E, count, 2]}, got {list(value.shape)}")
        if ((value < 0) | (value > grid_max)).any():
            raise ValueError(f"{name} must lie on the {c.width} x {c.height} grid (x < width, y < height)")
        cells.append(value[..., 0] * c.height + value[..., 1])
    starts, no_fly, targets = cells
    for name, group in (
        ("uav_positions", starts),
        ("no_fly_positions + target_positions", torch.cat([no_fly, targets], 1)),
    ):
        ordered = group.sort(dim=1).values
        if (ordered[:, 1:] == ordered[:, :-1]).any():
            raise ValueError(f"{name} must be distinct cells")
    if (starts.unsqueeze(-1) == no_fly.unsqueeze(-2)).any():
        raise ValueError("uav_positions must not be on no-fly cells")
    return starts, no_fly, targets
