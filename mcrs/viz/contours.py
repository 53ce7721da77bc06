"""The paper's figure 4: one UAV's uncertainty map m(U) as contours, with and without communication."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from tensordict import TensorDictBase

from mcrs.env.canvas import UNCERTAINTY_CMAP, as_image, new_figure, setup_grid
from mcrs.env.config import EnvConfig
from mcrs.viz.frames import episode_frames


def default_contour_steps(env_config: EnvConfig) -> tuple[int, int]:
    """Return half way and the end of the episode, the two moments of the paper's figure 4."""
    return (env_config.max_steps // 2, env_config.max_steps)


def uncertainty_contour_data(
    episode: TensorDictBase, env_config: EnvConfig, uav: int = 0, steps: Sequence[int] | None = None
) -> np.ndarray:
    """Return UAV ``uav``'s own fused m(U) maps ``[len(steps), W, H]`` after each of ``steps``."""
    fr = episode_frames(episode, env_config)
    steps = default_contour_steps(env_config) if steps is None else steps
    if not 0 <= uav < env_config.n_uavs:
        raise ValueError(f"uav={uav} out of range 0..{env_config.n_uavs - 1}")
    bad = [s for s in steps if not 0 <= s <= fr.steps]
    if bad:
        raise ValueError(f"steps {bad} out of range 0..{fr.steps}")
    return np.stack([fr.beliefs[s, uav, 0] for s in steps])


def plot_uncertainty_contours(
    with_comm: TensorDictBase,
    without_comm: TensorDictBase,
    env_config: EnvConfig,
    path: str | Path | None = None,
    uav: int = 0,
    steps: Sequence[int] | None = None,
) -> Figure:
    """Draw paper figure 4: one UAV's m(U) contours with and without communication, one column per step.
    ``without_comm`` must come from the same config with ``comm_range=0`` (:func:`rollout_comm_pair`). The
    UAV's trail is drawn on top."""
    steps = tuple(default_contour_steps(env_config) if steps is None else steps)
    rows = [
        ("with communication", with_comm, env_config.comm_range),
        ("without communication", without_comm, 0.0),
    ]
    fig = new_figure(3.6 * len(steps) + 1.2, 6.6)
    axes = fig.subplots(2, len(steps), squeeze=False)
    levels = np.linspace(0.0, 1.0, 11)
    x, y = np.arange(env_config.width), np.arange(env_config.height)
    contour = None
    for r, (label, episode, comm_range) in enumerate(rows):
        fr = episode_frames(episode, env_config)
        data = uncertainty_contour_data(episode, env_config, uav, steps)
        for c, step in enumerate(steps):
            ax = axes[r, c]
            setup_grid(ax, env_config, cell_lines=False)
            ax.set_xlim(0, env_config.width - 1)  # contours live on cell centres
            ax.set_ylim(0, env_config.height - 1)
            contour = ax.contourf(
                x, y, as_image(data[c]), levels=levels, cmap=UNCERTAINTY_CMAP, vmin=0, vmax=1
            )
            ax.scatter(*fr.no_fly.T, marker="s", s=30, facecolors="none", edgecolors="k", lw=1.0, zorder=3)
            ax.plot(*fr.positions[: step + 1, uav].T, c="k", lw=0.8, alpha=0.6, zorder=4)
            ax.scatter(*fr.positions[step, uav], marker="^", s=60, c="yellow", edgecolors="k", zorder=5)
            letter = "abcdefghijklmnop"[r * len(steps) + c]
            ax.set_title(
                f"({letter}) {label}, R_c={comm_range:g}\nstep {step}: mean m(U) {data[c].mean():.2f}",
                fontsize=9,
            )
    fig.colorbar(contour, ax=axes, shrink=0.8, label=f"UAV {uav}'s m(U)")
    fig.suptitle(
        f"{env_config.name}: uncertainty map of UAV {uav} (squares: no-fly, triangle: UAV)", fontsize=10
    )
    if path is not None:
        fig.savefig(path, dpi=120)
    return fig
