"""Shared drawing helpers: an Agg figure that never touches the global pyplot backend, the grid and the
colours.

They live in the environment layer so that ``render()`` and the pictures of mcrs.viz draw with the same
code. Cell (x, y) is drawn at x horizontally and y upwards, so that the paper's action names match the
picture."""

from __future__ import annotations

import numpy as np
from matplotlib import colormaps
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from mcrs.env.config import EnvConfig

UNCERTAINTY_CMAP = "coolwarm"  # paper figure 4: red = uncertain, blue = known
NO_FLY_COLOR = "#b2182b"
FOUND_COLOR = "#1a9850"
MISSED_COLOR = "#f46d43"


def new_figure(width: float, height: float) -> Figure:
    """A figure on its own Agg canvas (inches), never registered with pyplot."""
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def setup_grid(ax: Axes, cfg: EnvConfig, cell_lines: bool = True) -> None:
    """Axes over the map's cells (centres at integers), square cells, optional cell borders."""
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


def as_image(values: np.ndarray) -> np.ndarray:
    """Turn a ``[W, H]`` map indexed [x, y] into image rows y and columns x, for ``origin="lower"``."""
    return values.T


def extent(cfg: EnvConfig) -> tuple[float, float, float, float]:
    """``imshow``'s extent that puts each map value on its cell."""
    return (-0.5, cfg.width - 0.5, -0.5, cfg.height - 0.5)


#: No-fly cells over a coloured belief map (the GIF): dark, opaque, white-hatched, so that they stand out
#: from both ends of the red-blue scale; over the scene's grey map the red of NO_FLY_COLOR is clear.
NO_FLY_ON_MAP = {"facecolor": "0.12", "edgecolor": "white", "alpha": 0.9, "hatch": "xx", "linewidth": 0.8}


def draw_no_fly(ax: Axes, no_fly: np.ndarray, **style) -> None:
    """Hatched squares on the no-fly cells ``[Z, 2]`` (``style``: patch keywords, e.g. NO_FLY_ON_MAP)."""
    style = {"facecolor": NO_FLY_COLOR, "alpha": 0.35, "edgecolor": NO_FLY_COLOR, "hatch": "xx", **style}
    for x, y in no_fly:
        ax.add_patch(square(x, y, zorder=2, **style))


def square(x: float, y: float, **kwargs) -> Rectangle:
    """The unit square of cell (x, y)."""
    return Rectangle((x - 0.5, y - 0.5), 1.0, 1.0, **kwargs)


def uav_colors(n: int) -> list:
    """One qualitative colour per UAV (repeating beyond 20)."""
    cmap = colormaps["tab10" if n <= 10 else "tab20"]
    return [cmap(i % cmap.N) for i in range(n)]


def trail_offsets(n: int) -> np.ndarray:
    """Small per-UAV shifts so that trails sharing a cell stay distinguishable."""
    angles = 2 * np.pi * np.arange(n) / max(n, 1)
    return 0.18 * np.stack([np.cos(angles), np.sin(angles)], -1)
