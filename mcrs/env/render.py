"""Draw one state of the map as an RGB array: m(U) behind the UAVs, their trails, links, no-fly cells and
targets.

The PettingZoo adapter's ``render()``, the episode GIF of ``mcrs-render`` and the evaluation video all use
this one routine, so they show the same thing. The axis decorations take most of the drawing time, so they
are drawn once and each frame redraws only the content (blitting); every frame then has the same size, as a
video needs."""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np
import torch
from matplotlib.axis import Axis
from matplotlib.colors import Normalize
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from PIL import Image
from tensordict import TensorDictBase

from mcrs.env.canvas import (
    FOUND_COLOR,
    NO_FLY_ON_MAP,
    UNCERTAINTY_CMAP,
    as_image,
    draw_no_fly,
    extent,
    new_figure,
    setup_grid,
    trail_offsets,
    uav_colors,
)
from mcrs.env.config import EnvConfig
from mcrs.env.layout import StateLayout


@dataclass
class EpisodeFrames:
    """The per-step arrays of one episode as numpy, from step 0 (after reset) to step T inclusive."""

    positions: np.ndarray  # [T+1, N, 2] int
    global_maps: np.ndarray  # [T+1, 2, W, H]: global m(U), m(F)
    beliefs: np.ndarray  # [T+1, N, 2, W, H]: each UAV's fused m(U), m(F)
    neighbours: np.ndarray  # [T+1, N, N] bool
    no_fly: np.ndarray  # [Z, 2] int
    targets: np.ndarray  # [K, 2] int
    rewards: np.ndarray  # [T+1] cumulative episode reward
    config: EnvConfig

    @property
    def steps(self) -> int:
        return self.positions.shape[0] - 1

    def found(self, step: int) -> np.ndarray:
        """``[W, H]`` bool: cells whose global m(F) has reached tau by ``step``, target or not."""
        full = self.global_maps[: step + 1, 1]
        return (full >= self.config.target_threshold).any(0)


def episode_frames(episode: TensorDictBase, env_config: EnvConfig, env: int = 0) -> EpisodeFrames:
    """Unpack environment ``env`` of a rollout taken with ``expose_beliefs=True`` into per-step arrays, reset
    included."""
    if ("agents", "belief_map") not in episode.keys(include_nested=True):
        raise ValueError("the episode has no belief maps: roll it out with expose_beliefs=True")
    first, last = episode[env], episode[env]["next"]

    def steps(key: str | tuple[str, ...]) -> np.ndarray:
        return torch.cat([first.get(key), last.get(key)[-1:]]).cpu().numpy()

    layout = StateLayout.from_config(env_config)
    state = first.get("state")[0]
    reward = episode[env]["next", "metrics", "episode_reward"]
    return EpisodeFrames(
        positions=steps(("agents", "position")),
        global_maps=steps("state_map"),
        beliefs=steps(("agents", "belief_map")),
        neighbours=steps("neighbours"),
        no_fly=layout.cells(state, layout.no_fly_position).cpu().numpy(),
        targets=layout.cells(state, layout.target_position).cpu().numpy(),
        rewards=np.concatenate([[0.0], reward.cpu().numpy()]),
        config=env_config,
    )


def frame_title(cfg: EnvConfig, step: int, uncertainty: np.ndarray, reward: float) -> str:
    return f"{cfg.name} step {step}/{cfg.max_steps}: sum m(U) {uncertainty.sum():.1f}, reward {reward:.1f}"


class StateDrawing:
    """A figure of one map, redrawn state by state; :meth:`draw` returns an ``[H, W, 3]`` uint8 frame.

    Args:
        no_fly, targets: ``[Z, 2]`` and ``[K, 2]`` cells, fixed for an episode.
        label: the colour bar's label, naming the background map.
        trail: how many past steps of each UAV's path to draw; None draws all.
        dpi: resolution; 80 gives a 512 x 496 frame.
    """

    def __init__(
        self,
        cfg: EnvConfig,
        no_fly: np.ndarray,
        targets: np.ndarray,
        label: str = "global m(U)",
        trail: int | None = 12,
        dpi: int = 80,
    ) -> None:
        self.cfg, self.trail = cfg, trail
        self.targets = np.asarray(targets, dtype=np.int64).reshape(-1, 2)
        fig = new_figure(6.4, 6.2)
        ax = fig.add_subplot()
        setup_grid(ax, cfg)
        self.image = ax.imshow(
            np.ones((cfg.height, cfg.width)),
            origin="lower",
            extent=extent(cfg),
            cmap=UNCERTAINTY_CMAP,
            norm=Normalize(0.0, 1.0),
            zorder=0,
        )
        bar = fig.colorbar(self.image, ax=ax, shrink=0.8, label=f"{label} (the belief colour scale)")
        bar.set_ticks([0.0, 0.5, 1.0], labels=["0 known", "0.5", "1 uncertain"])
        draw_no_fly(ax, np.asarray(no_fly).reshape(-1, 2), **NO_FLY_ON_MAP)  # dark: clear on red and blue
        self.target_marks = ax.scatter(
            *self.targets.T, marker="*", s=180, facecolors="none", edgecolors="k", lw=1.2, zorder=5
        )
        n = cfg.n_uavs
        colors, self.shift = uav_colors(n), trail_offsets(n)
        self.trails = [ax.plot([], [], c=colors[i], lw=1.5, zorder=4)[0] for i in range(n)]
        self.uavs = ax.scatter(np.zeros(n), np.zeros(n), s=80, c=colors, edgecolors="k", zorder=6)
        self.pairs = list(zip(*np.triu_indices(n, 1), strict=True))
        self.links = [ax.plot([], [], ls="--", lw=1.0, c="k", zorder=3)[0] for _ in self.pairs]
        # The legend is outside the axes: drawn once with the decorations, not redrawn per frame.
        fig.legend(
            handles=legend(cfg, colors), loc="outside lower center", ncols=3, fontsize=8, frameon=False
        )
        # The widest title an episode can have, so that the layout frozen below fits every frame.
        widest = frame_title(cfg, cfg.max_steps, np.full(cfg.n_cells, 1.0), -99999.9)
        self.title = ax.set_title(widest, fontsize=10)
        fig.set_dpi(dpi)
        fig.canvas.draw()
        fig.set_layout_engine("none")
        # The axes background patch first (a full draw does the same), then the rest by z-order.
        self.content = sorted(
            (a for a in ax.get_children() if not isinstance(a, Axis)),
            key=lambda a: (a is not ax.patch, a.get_zorder()),
        )
        title_position = ax.title.get_position()
        for artist in self.content:
            artist.set_visible(False)
        fig.canvas.draw()
        self.decorations = fig.canvas.copy_from_bbox(fig.bbox)
        for artist in self.content:
            artist.set_visible(True)
        ax.title.set_position(title_position)  # the draw of an empty axes moved it
        self.fig, self.ax = fig, ax

    def draw(
        self,
        background: np.ndarray,
        positions: np.ndarray,
        neighbours: np.ndarray,
        found: np.ndarray,
        title: str,
    ) -> np.ndarray:
        """Draw one frame and return it as ``[H, W, 3]`` uint8. ``background`` is ``[W, H]`` in [0, 1],
        ``positions`` ``[t+1, N, 2]`` the path so far with the current row last, ``neighbours`` ``[N, N]``
        bool and ``found`` ``[W, H]`` the cells whose m(F) reached tau."""
        self.image.set_data(as_image(background))
        now = positions[-1]
        recent = positions if self.trail is None else positions[-(self.trail + 1) :]
        for i, line in enumerate(self.trails):
            line.set_data(*(recent[:, i] + self.shift[i]).T)
        self.uavs.set_offsets(now)
        for line, (i, j) in zip(self.links, self.pairs, strict=True):
            ends = np.stack([now[i], now[j]])
            line.set_data(*(ends.T if neighbours[i, j] else ([], [])))
        if len(self.targets):
            hit = found[self.targets[:, 0], self.targets[:, 1]]
            self.target_marks.set_facecolors([FOUND_COLOR if h else "none" for h in hit])
        self.title.set_text(title)
        canvas = self.fig.canvas
        canvas.restore_region(self.decorations)
        for artist in self.content:
            self.ax.draw_artist(artist)
        return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def legend(cfg: EnvConfig, colors: list) -> list:
    """Return the legend entries of a frame: UAVs and trails, targets, no-fly zones and links."""
    return [
        Line2D([], [], marker="o", ls="-", c=colors[0], mec="k", ms=8, label=f"UAV and its trail ({cfg.n_uavs}, one colour each)"),
        Line2D([], [], marker="*", ls="", mfc="none", mec="k", ms=13, label="target, not yet found"),
        Line2D([], [], marker="*", ls="", mfc=FOUND_COLOR, mec="k", ms=13, label="target found"),
        Patch(**{**NO_FLY_ON_MAP, "label": "no-fly zone"}),
        Line2D([], [], ls="--", lw=1.0, c="k", label=f"comm link (R_c={cfg.comm_range:g})"),
    ]  # fmt: skip


def episode_rgb_frames(
    fr: EpisodeFrames, background: str | int = "global", trail: int | None = 12, dpi: int = 80
) -> list[np.ndarray]:
    """Return every step of an episode as ``[H, W, 3]`` uint8 frames, step 0 to T. ``background`` is
    ``"global"`` for the global map, or a UAV index for that UAV's own fused map."""
    cfg = fr.config
    if background == "global":
        maps, label = fr.global_maps[:, 0], "global m(U)"
    elif isinstance(background, int) and 0 <= background < cfg.n_uavs:
        maps, label = fr.beliefs[:, background, 0], f"UAV {background}'s m(U)"
    else:
        raise ValueError(
            f"background must be 'global' or a UAV index 0..{cfg.n_uavs - 1}, got {background!r}"
        )
    drawing = StateDrawing(cfg, fr.no_fly, fr.targets, label, trail, dpi)
    found = (fr.global_maps[:, 1] >= cfg.target_threshold).cumsum(0) > 0  # [T+1, W, H]: found by step t
    return [
        drawing.draw(
            maps[t],
            fr.positions[: t + 1],
            fr.neighbours[t],
            found[t],
            frame_title(cfg, t, maps[t], float(fr.rewards[t])),
        )
        for t in range(fr.steps + 1)
    ]


def encode_gif(frames: list[np.ndarray], fps: int = 5) -> bytes:
    """Encode ``[H, W, 3]`` uint8 frames as a looping GIF, the format of the episode GIF and the video."""
    if not frames:
        raise ValueError("encode_gif needs at least one frame")
    images = [Image.fromarray(frame) for frame in frames]
    out = io.BytesIO()
    images[0].save(
        out, format="GIF", save_all=True, append_images=images[1:], duration=round(1000 / fps), loop=0
    )
    return out.getvalue()
