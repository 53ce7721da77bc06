"""An animated GIF of one episode: an m(U) map behind the UAVs, their trails, no-fly cells and targets."""

from __future__ import annotations

from pathlib import Path

from tensordict import TensorDictBase

from mcrs.env.config import EnvConfig
from mcrs.env.render import encode_gif, episode_rgb_frames
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
    trail; a short one keeps large maps readable). The frames are those of
    :func:`mcrs.env.render.episode_rgb_frames`, the same drawing as the adapter's ``render()``.
    """
    frames = episode_rgb_frames(episode_frames(episode, env_config), background, trail, dpi)
    path = Path(path)
    path.write_bytes(encode_gif(frames, fps))
    return path
