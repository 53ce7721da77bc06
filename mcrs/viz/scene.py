"""The whole episode on one picture: trails, no-fly cells, targets found or missed, last-step links."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from tensordict import TensorDictBase

from mcrs.env.canvas import (
    FOUND_COLOR,
    MISSED_COLOR,
    NO_FLY_COLOR,
    as_image,
    draw_no_fly,
    extent,
    new_figure,
    setup_grid,
    trail_offsets,
    uav_colors,
)
from mcrs.env.config import EnvConfig
from mcrs.viz.frames import episode_frames


def plot_scene(episode: TensorDictBase, env_config: EnvConfig, path: str | Path | None = None) -> Figure:
    """Draw the whole episode over the final global m(U), so unexplored parts stand out."""
    fr = episode_frames(episode, env_config)
    cfg, T = env_config, fr.steps
    fig = new_figure(6.8, 7.0)
    ax = fig.add_subplot()
    setup_grid(ax, cfg)
    image = ax.imshow(
        as_image(fr.global_maps[T, 0]),
        origin="lower",
        extent=extent(cfg),
        cmap="Greys",
        norm=Normalize(0.0, 1.0),
        alpha=0.45,
        zorder=0,
    )
    fig.colorbar(image, ax=ax, shrink=0.7, fraction=0.04, label="final global m(U) (white: known)")
    draw_no_fly(ax, fr.no_fly)

    found = fr.found(T)
    is_target = np.zeros((cfg.width, cfg.height), dtype=bool)
    if len(fr.targets):
        is_target[fr.targets[:, 0], fr.targets[:, 1]] = True
        hit = found[fr.targets[:, 0], fr.targets[:, 1]]
        ax.scatter(*fr.targets[hit].T, marker="*", s=220, c=FOUND_COLOR, edgecolors="k", zorder=5)
        ax.scatter(
            *fr.targets[~hit].T,
            marker="*",
            s=220,
            facecolors="none",
            edgecolors=MISSED_COLOR,
            linewidths=1.6,
            zorder=5,
        )
    false_hits = np.argwhere(found & ~is_target)
    if len(false_hits):
        ax.scatter(*false_hits.T, marker="x", s=70, c="k", zorder=5)

    final = fr.positions[T]
    links = np.argwhere(np.triu(fr.neighbours[T], 1))
    for i, j in links:
        ax.plot(*np.stack([final[i], final[j]]).T, ls="--", lw=1.2, c="0.3", zorder=3)

    colors, shift = uav_colors(cfg.n_uavs), trail_offsets(cfg.n_uavs)
    for i in range(cfg.n_uavs):
        trail = fr.positions[:, i] + shift[i]
        ax.plot(*trail.T, c=colors[i], lw=1.4, alpha=0.85, zorder=4)
        ax.scatter(*trail[0], marker="o", s=45, facecolors="white", edgecolors=colors[i], lw=1.5, zorder=6)
        ax.scatter(*trail[-1], marker="o", s=70, c=[colors[i]], edgecolors="k", zorder=6)
        ax.annotate(str(i), trail[-1], xytext=(4, 4), textcoords="offset points", fontsize=8, zorder=7)

    legend = [
        Line2D([], [], marker="o", ls="", mfc="white", mec="0.2", label="start"),
        Line2D([], [], marker="o", ls="", mfc="0.5", mec="k", label=f"UAV at step {T}"),
        Line2D(
            [],
            [],
            marker="s",
            ls="",
            mfc=NO_FLY_COLOR,
            alpha=0.5,
            mec=NO_FLY_COLOR,
            ms=10,
            label="no-fly zone",
        ),
        Line2D([], [], marker="*", ls="", mfc=FOUND_COLOR, mec="k", ms=13, label="target found"),
        Line2D([], [], marker="*", ls="", mfc="none", mec=MISSED_COLOR, ms=13, label="target missed"),
        Line2D([], [], marker="x", ls="", c="k", label="false discovery"),
        Line2D([], [], ls="--", c="0.3", label=f"comm link (R_c={cfg.comm_range:g})"),
    ]
    fig.legend(handles=legend, loc="outside lower center", ncols=4, fontsize=8, frameon=False)
    n_found = int(found[is_target].sum())
    ax.set_title(
        f"{cfg.name}: {n_found}/{len(fr.targets)} targets found, reward {fr.rewards[T]:.1f}, "
        f"coverage {(fr.global_maps[T, 0] < 1).mean():.0%}",
        fontsize=10,
    )
    if path is not None:
        fig.savefig(path, dpi=120)
    return fig
