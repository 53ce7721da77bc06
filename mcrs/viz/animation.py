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
    """Animate the episode with the frames of :func:`mcrs.env.render.episode_rgb_frames`. ``background`` is
    ``"global"`` or a UAV index for that UAV's own fused map. ``trail`` is how many past steps of trail to
    draw, None for all; a short one keeps large maps readable."""
    frames = episode_rgb_frames(episode_frames(episode, env_config), background, trail, dpi)
    path = Path(path)
    path.write_bytes(encode_gif(frames, fps))
    return path
