"""An animated GIF of one episode: an m(U) map behind the UAVs, their trails, no-fly cells and targets."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.axis import Axis
from matplotlib.colors import Normalize
from PIL import Image
from tensordict import TensorDictBase

from mcrs.env.config import EnvConfig
from mcrs.viz.canvas import (
    FOUND_COLOR,
    UNCERTAINTY_CMAP,
    as_image,
    draw_no_fly,
    extent,
    new_figure,
    setup_grid,
    trail_offsets,
    uav_colors,
)
from mcrs.viz.frames import episode_frames


def save_episode_gif(
    episode: TensorDictBase,
    env_config: EnvConfig,
    path: str | Path,
    background: str | int = "global",
    fps: int = 5,
    trail: int | None = 12,
    dpi: int = 80,
) -> Path:
    """Animate the episode: an m(U) map behind the UAVs, their trails, no-fly cells and targets.

    ``background`` is ``"global"`` (the global map of all detections) or a UAV index (that UAV's own
    fused map, i.e. what it knows). ``trail`` keeps the trails to the last steps (None: the whole
    trail; a short one keeps large maps readable).
    """
    fr = episode_frames(episode, env_config)
    cfg = env_config
    if background == "global":
        maps, label = fr.global_maps[:, 0], "global m(U)"
    elif isinstance(background, int) and 0 <= background < cfg.n_uavs:
        maps, label = fr.beliefs[:, background, 0], f"UAV {background}'s m(U)"
    else:
        raise ValueError(
            f"background must be 'global' or a UAV index 0..{cfg.n_uavs - 1}, got {background!r}"
        )

    fig = new_figure(6.4, 5.4)
    ax = fig.add_subplot()
    setup_grid(ax, cfg)
    image = ax.imshow(
        as_image(maps[0]),
        origin="lower",
        extent=extent(cfg),
        cmap=UNCERTAINTY_CMAP,
        norm=Normalize(0.0, 1.0),
        zorder=0,
    )
    fig.colorbar(image, ax=ax, shrink=0.8, label=label)
    draw_no_fly(ax, fr.no_fly)
    targets = ax.scatter(
        *fr.targets.T, marker="*", s=180, facecolors="none", edgecolors="k", lw=1.2, zorder=5
    )
    colors, shift = uav_colors(cfg.n_uavs), trail_offsets(cfg.n_uavs)
    trails = [ax.plot([], [], c=colors[i], lw=1.5, zorder=4)[0] for i in range(cfg.n_uavs)]
    uavs = ax.scatter(*fr.positions[0].T, s=80, c=colors, edgecolors="k", zorder=6)
    links = [
        ax.plot([], [], ls="--", lw=1.0, c="k", zorder=3)[0]
        for _ in range(cfg.n_uavs * (cfg.n_uavs - 1) // 2)
    ]
    pairs = list(zip(*np.triu_indices(cfg.n_uavs, 1), strict=True))
    title = ax.set_title("", fontsize=10)

    def draw(t: int) -> None:
        image.set_data(as_image(maps[t]))
        start = 0 if trail is None else max(0, t - trail)
        for i, line in enumerate(trails):
            line.set_data(*(fr.positions[start : t + 1, i] + shift[i]).T)
        uavs.set_offsets(fr.positions[t])
        for line, (i, j) in zip(links, pairs, strict=True):
            ends = np.stack([fr.positions[t, i], fr.positions[t, j]])
            line.set_data(*(ends.T if fr.neighbours[t, i, j] else ([], [])))
        if len(fr.targets):
            hit = fr.found(t)[fr.targets[:, 0], fr.targets[:, 1]]
            targets.set_facecolors([FOUND_COLOR if h else "none" for h in hit])
        title.set_text(
            f"{cfg.name} step {t}/{fr.steps}: sum m(U) {maps[t].sum():.1f}, reward {fr.rewards[t]:.1f}"
        )

    # Blitting: the axis decorations (ticks, labels, colour bar: most of the drawing time) are drawn once;
    # every frame restores them and redraws only the axes' content.
    fig.set_dpi(dpi)
    draw(fr.steps)  # the widest title, so that the frozen layout fits every frame
    fig.canvas.draw()
    fig.set_layout_engine("none")
    # The axes background patch first (a full draw does the same), then the rest by z-order.
    content = sorted(
        (a for a in ax.get_children() if not isinstance(a, Axis)),
        key=lambda a: (a is not ax.patch, a.get_zorder()),
    )
    title_position = ax.title.get_position()
    for artist in content:
        artist.set_visible(False)
    canvas = fig.canvas
    canvas.draw()
    decorations = canvas.copy_from_bbox(fig.bbox)
    for artist in content:
        artist.set_visible(True)
    ax.title.set_position(title_position)  # the draw of an empty axes moved it
    frames = []
    for t in range(fr.steps + 1):
        draw(t)
        canvas.restore_region(decorations)
        for artist in content:
            ax.draw_artist(artist)
        frames.append(Image.fromarray(np.asarray(canvas.buffer_rgba())).convert("RGB"))
    path = Path(path)
    frames[0].save(
        path, format="GIF", save_all=True, append_images=frames[1:], duration=round(1000 / fps), loop=0
    )
    return path
