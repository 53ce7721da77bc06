"""The pictures of one episode, as ``mcrs-eval figures=true`` and ``mcrs-render`` both write them."""

from __future__ import annotations

from pathlib import Path

from mcrs.env.config import EnvConfig
from mcrs.viz.animation import save_episode_gif
from mcrs.viz.contours import plot_uncertainty_contours
from mcrs.viz.frames import rollout_comm_pair
from mcrs.viz.scene import plot_scene

SCENE, CONTOURS, GIF = "scene.png", "uncertainty_contours.png", "episode.gif"


def write_episode_pictures(
    out_dir: str | Path,
    env_config: EnvConfig,
    policy: str,
    seed: int,
    gif: bool = True,
    uav: int = 0,
) -> list[Path]:
    """Roll out one episode of ``policy`` from ``seed`` and write its pictures into ``out_dir``; return the
    paths. They are ``scene.png``, ``uncertainty_contours.png`` (figure 4 for UAV ``uav``) and, with
    ``gif``, ``episode.gif``. ``policy`` is anything :func:`mcrs.policies.make_policy` takes."""
    if not 0 <= uav < env_config.n_uavs:
        raise ValueError(
            f"uav={uav}: must be in 0..{env_config.n_uavs - 1} (the map has {env_config.n_uavs} UAVs)"
        )
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    episode, without = rollout_comm_pair(env_config, policy, seed)
    paths = [out_dir / SCENE, out_dir / CONTOURS]
    plot_scene(episode, env_config, paths[0])
    plot_uncertainty_contours(episode, without, env_config, paths[1], uav=uav)
    if gif:
        paths.append(save_episode_gif(episode, env_config, out_dir / GIF))
    return paths
