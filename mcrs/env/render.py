"""Pictures of one episode: the scene, the paper's figure 4 (uncertainty contours) and an animation.

Everything is drawn from a rollout with ``expose_beliefs=True`` (:func:`rollout_episode`), through the
object-oriented matplotlib API on an Agg canvas: importing this module never touches the global
pyplot backend, so it is safe in notebooks, tests and headless servers alike.

Grid convention: cell (x, y) is drawn at x horizontally and y vertically, y growing upwards, so that
the action names of the paper (left, up, ...) match the picture.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from matplotlib import colormaps
from matplotlib.axes import Axes
from matplotlib.axis import Axis
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Rectangle
from PIL import Image
from tensordict import TensorDictBase

from mcrs.env.config import EnvConfig
from mcrs.env.layout import StateLayout
from mcrs.env.torchrl_env import MCRSEnv
from mcrs.policies import make_policy

UNCERTAINTY_CMAP = "coolwarm"  # paper figure 4: red = uncertain, blue = known
NO_FLY_COLOR = "#b2182b"
FOUND_COLOR = "#1a9850"
MISSED_COLOR = "#f46d43"


def rollout_episode(env_config: EnvConfig, policy_name: str, seed: int) -> TensorDictBase:
    """One full episode (``max_steps`` steps, one env, beliefs exposed): a ``[1, T]`` tensordict."""
    cfg = env_config.replace(num_envs=1, expose_beliefs=True)
    env = MCRSEnv(cfg)
    env.set_seed(seed)
    policy = make_policy(policy_name, cfg, seed)
    with torch.no_grad():
        return env.rollout(cfg.max_steps, policy, break_when_any_done=False)


@dataclass
class EpisodeFrames:
    """The per-step arrays of one episode as numpy, step 0 (after reset) to step T inclusive."""

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
        """``[W, H]`` bool: cells whose global m(F) has reached tau by ``step`` (found or false)."""
        full = self.global_maps[: step + 1, 1]
        return (full >= self.config.target_threshold).any(0)


def episode_frames(episode: TensorDictBase, env_config: EnvConfig) -> EpisodeFrames:
    """Unpack a :func:`rollout_episode` result (env 0) into per-step arrays, reset included."""
    if ("agents", "belief_map") not in episode.keys(include_nested=True):
        raise ValueError("the episode has no belief maps: roll it out with expose_beliefs=True")
    first, last = episode[0], episode[0]["next"]

    def steps(key: str | tuple[str, ...]) -> np.ndarray:
        return torch.cat([first.get(key), last.get(key)[-1:]]).cpu().numpy()

    layout = StateLayout.from_config(env_config)
    state = first.get("state")[0]
    reward = episode[0]["next", "metrics", "episode_reward"]
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


# ---------------------------------------------------------------------------------------------- helpers
def _new_figure(width: float, height: float) -> Figure:
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _setup_grid(ax: Axes, cfg: EnvConfig, cell_lines: bool = True) -> None:
    ax.set_xlim(-0.5, cfg.width - 0.5)
    ax.set_ylim(-0.5, cfg.height - 0.5)
    ax.set_aspect("equal")
    ax.set_xticks(np.arange(0, cfg.width, max(1, cfg.width // 10)))
    ax.set_yticks(np.arange(0, cfg.height, max(1, cfg.height // 10)))
    if cell_lines:  # explicit lines: minor ticks would cost a tick-label layout on every animation frame
        ax.vlines(np.arange(-0.5, cfg.width), -0.5, cfg.height - 0.5, colors="0.85", linewidths=0.5, zorder=1)
        ax.hlines(np.arange(-0.5, cfg.height), -0.5, cfg.width - 0.5, colors="0.85", linewidths=0.5, zorder=1)
    ax.set_xlabel("x")
    ax.set_ylabel("y")


def _image(values: np.ndarray) -> np.ndarray:
    """``[W, H]`` map indexed [x, y] -> image rows y, columns x (for ``origin="lower"``)."""
    return values.T


def _extent(cfg: EnvConfig) -> tuple[float, float, float, float]:
    return (-0.5, cfg.width - 0.5, -0.5, cfg.height - 0.5)


def _draw_no_fly(ax: Axes, no_fly: np.ndarray) -> None:
    for x, y in no_fly:
        ax.add_patch(
            _square(x, y, facecolor=NO_FLY_COLOR, alpha=0.35, edgecolor=NO_FLY_COLOR, hatch="xx", zorder=2)
        )


def _square(x: float, y: float, **kwargs) -> Rectangle:
    return Rectangle((x - 0.5, y - 0.5), 1.0, 1.0, **kwargs)


def _uav_colors(n: int) -> list:
    cmap = colormaps["tab10" if n <= 10 else "tab20"]
    return [cmap(i % cmap.N) for i in range(n)]


def _offsets(n: int) -> np.ndarray:
    """Small per-UAV shifts so that trails sharing a cell stay distinguishable."""
    angles = 2 * np.pi * np.arange(n) / max(n, 1)
    return 0.18 * np.stack([np.cos(angles), np.sin(angles)], -1)


# ---------------------------------------------------------------------------------------------- scene
def plot_scene(episode: TensorDictBase, env_config: EnvConfig, path: str | Path | None = None) -> Figure:
    """The whole episode on one picture: trails, no-fly cells, targets found/missed, last-step links.

    The background is the final global m(U), so unexplored parts of the map stand out.
    """
    fr = episode_frames(episode, env_config)
    cfg, T = env_config, fr.steps
    fig = _new_figure(6.8, 7.0)
    ax = fig.add_subplot()
    _setup_grid(ax, cfg)
    image = ax.imshow(
        _image(fr.global_maps[T, 0]),
        origin="lower",
        extent=_extent(cfg),
        cmap="Greys",
        norm=Normalize(0.0, 1.0),
        alpha=0.45,
        zorder=0,
    )
    fig.colorbar(image, ax=ax, shrink=0.7, fraction=0.04, label="final global m(U) (white: known)")
    _draw_no_fly(ax, fr.no_fly)

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

    colors, shift = _uav_colors(cfg.n_uavs), _offsets(cfg.n_uavs)
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


# ---------------------------------------------------------------------------------------------- figure 4
def default_contour_steps(env_config: EnvConfig) -> tuple[int, int]:
    """Half way and the end of the episode, as the two moments of the paper's figure 4."""
    return (env_config.max_steps // 2, env_config.max_steps)


def uncertainty_contour_data(
    episode: TensorDictBase, env_config: EnvConfig, uav: int = 0, steps: Sequence[int] | None = None
) -> np.ndarray:
    """``[len(steps), W, H]``: UAV ``uav``'s own fused m(U) map after each of ``steps``."""
    fr = episode_frames(episode, env_config)
    steps = default_contour_steps(env_config) if steps is None else steps
    if not 0 <= uav < env_config.n_uavs:
        raise ValueError(f"uav={uav} out of range 0..{env_config.n_uavs - 1}")
    bad = [s for s in steps if not 0 <= s <= fr.steps]
    if bad:
        raise ValueError(f"steps {bad} out of range 0..{fr.steps}")
    return np.stack([fr.beliefs[s, uav, 0] for s in steps])


def rollout_comm_pair(
    env_config: EnvConfig, policy_name: str, seed: int
) -> tuple[TensorDictBase, TensorDictBase]:
    """The same episode seed with the config's communication and without any (``comm_range=0``)."""
    with_comm = rollout_episode(env_config, policy_name, seed)
    without = rollout_episode(env_config.replace(comm_range=0.0), policy_name, seed)
    return with_comm, without


def plot_uncertainty_contours(
    with_comm: TensorDictBase,
    without_comm: TensorDictBase,
    env_config: EnvConfig,
    path: str | Path | None = None,
    uav: int = 0,
    steps: Sequence[int] | None = None,
) -> Figure:
    """Paper figure 4: contour maps of one UAV's m(U), rows with / without communication, one column a step.

    ``without_comm`` must come from the same config with ``comm_range=0`` (see :func:`rollout_comm_pair`).
    The UAV's trail up to each step is drawn on top, so one sees what it learned by itself.
    """
    steps = tuple(default_contour_steps(env_config) if steps is None else steps)
    rows = [
        ("with communication", with_comm, env_config.comm_range),
        ("without communication", without_comm, 0.0),
    ]
    fig = _new_figure(3.6 * len(steps) + 1.2, 6.6)
    axes = fig.subplots(2, len(steps), squeeze=False)
    levels = np.linspace(0.0, 1.0, 11)
    x, y = np.arange(env_config.width), np.arange(env_config.height)
    contour = None
    for r, (label, episode, comm_range) in enumerate(rows):
        fr = episode_frames(episode, env_config)
        data = uncertainty_contour_data(episode, env_config, uav, steps)
        for c, step in enumerate(steps):
            ax = axes[r, c]
            _setup_grid(ax, env_config, cell_lines=False)
            ax.set_xlim(0, env_config.width - 1)  # contours live on cell centres
            ax.set_ylim(0, env_config.height - 1)
            contour = ax.contourf(x, y, _image(data[c]), levels=levels, cmap=UNCERTAINTY_CMAP, vmin=0, vmax=1)
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


# ---------------------------------------------------------------------------------------------- animation
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

    fig = _new_figure(6.4, 5.4)
    ax = fig.add_subplot()
    _setup_grid(ax, cfg)
    image = ax.imshow(
        _image(maps[0]),
        origin="lower",
        extent=_extent(cfg),
        cmap=UNCERTAINTY_CMAP,
        norm=Normalize(0.0, 1.0),
        zorder=0,
    )
    fig.colorbar(image, ax=ax, shrink=0.8, label=label)
    _draw_no_fly(ax, fr.no_fly)
    targets = ax.scatter(
        *fr.targets.T, marker="*", s=180, facecolors="none", edgecolors="k", lw=1.2, zorder=5
    )
    colors, shift = _uav_colors(cfg.n_uavs), _offsets(cfg.n_uavs)
    trails = [ax.plot([], [], c=colors[i], lw=1.5, zorder=4)[0] for i in range(cfg.n_uavs)]
    uavs = ax.scatter(*fr.positions[0].T, s=80, c=colors, edgecolors="k", zorder=6)
    links = [
        ax.plot([], [], ls="--", lw=1.0, c="k", zorder=3)[0]
        for _ in range(cfg.n_uavs * (cfg.n_uavs - 1) // 2)
    ]
    pairs = list(zip(*np.triu_indices(cfg.n_uavs, 1), strict=True))
    title = ax.set_title("", fontsize=10)

    def draw(t: int) -> None:
        image.set_data(_image(maps[t]))
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
