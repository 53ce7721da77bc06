"""Pictures of one episode: the scene, the paper's figure 4 (uncertainty contours) and an animation.

Everything is drawn from a rollout with ``expose_beliefs=True`` on an Agg canvas, never the global pyplot
backend, so it is safe in notebooks, tests and headless servers. :func:`write_episode_pictures` is the
routine behind ``mcrs-eval figures=true`` and ``mcrs-render``."""

from mcrs.viz.animation import save_episode_gif
from mcrs.viz.contours import default_contour_steps, plot_uncertainty_contours, uncertainty_contour_data
from mcrs.viz.episode import write_episode_pictures
from mcrs.viz.frames import EpisodeFrames, episode_frames, rollout_comm_pair, rollout_episode
from mcrs.viz.scene import plot_scene

__all__ = [
    "EpisodeFrames",
    "default_contour_steps",
    "episode_frames",
    "plot_scene",
    "plot_uncertainty_contours",
    "rollout_comm_pair",
    "rollout_episode",
    "save_episode_gif",
    "uncertainty_contour_data",
    "write_episode_pictures",
]
