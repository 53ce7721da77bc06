"""Greedy evaluation of a trained agent on separate, fixed-seed environments of its task."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.record.loggers import Logger

from mcrs.env.config import EnvConfig
from mcrs.env.core import METRICS
from mcrs.experiment.logging import log_video
from mcrs.experiment.task import MCRSTask, Task, as_task, with_agent_state


def make_eval_env(
    env_config: EnvConfig | Task,
    episodes: int,
    hidden_dim: int,
    device: str | torch.device,
    expose_beliefs: bool = False,
) -> TransformedEnv:
    """``episodes`` environments of the task run as one batch, carrying the agents' recurrent state (with
    ``expose_beliefs``, MCRS only, also what an episode's pictures are drawn from)."""
    task = as_task(env_config)
    if isinstance(task, MCRSTask):
        env = task.make_env(episodes, torch.device(device), expose_beliefs=expose_beliefs)
    else:
        env = task.make_env(episodes, torch.device(device))
    return with_agent_state(env, task, episodes, hidden_dim, device)


@torch.no_grad()
def rollout_greedy(
    env: TransformedEnv, policy: TensorDictModuleBase, seed: int, max_steps: int | None = None
) -> TensorDictBase:
    """One episode (``max_steps``; default: the MCRS env's) in every environment of ``env`` from seed
    ``seed``, greedy actions: ``[E, T]``."""
    env.set_seed(seed)
    steps = env.base_env.config.max_steps if max_steps is None else max_steps
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        return env.rollout(steps, policy, break_when_any_done=False)


def episode_metrics(rollout: TensorDictBase, task: Task | None = None) -> dict[str, torch.Tensor]:
    """Final value of every metric per episode: ``{name: [E]}`` (``task.episode_metrics``; default MCRS's)."""
    if task is None:
        return {name: rollout.get(("next", "metrics", name))[:, -1].float() for name in METRICS}
    return task.episode_metrics(rollout)


def evaluate(
    env: TransformedEnv, policy: TensorDictModuleBase, seed: int, task: Task | None = None
) -> dict[str, float]:
    """Mean (and std of the episode reward) of every metric over the batch of episodes."""
    steps = None if task is None else task.max_steps
    metrics = episode_metrics(rollout_greedy(env, policy, seed, steps), task)
    out = {name: values.mean().item() for name, values in metrics.items()}
    out["episode_reward_std"] = metrics["episode_reward"].std(unbiased=False).item()
    return out


class EvaluationVideo:
    """``logger.video``: one greedy episode (the first evaluation seed, one environment with its beliefs
    exposed) drawn frame by frame as the episode GIF is, and logged as ``eval/video``."""

    def __init__(self, env_config: EnvConfig, hidden_dim: int, device: torch.device, seed: int) -> None:
        self.env_config, self.hidden_dim, self.device, self.seed = env_config, hidden_dim, device, seed
        self.env: TransformedEnv | None = None  # built on the first video

    def frames(self, policy: TensorDictModuleBase) -> list[np.ndarray]:
        """``[H, W, 3]`` uint8 frames, reset to the time limit."""
        from mcrs.env.render import episode_frames, episode_rgb_frames  # matplotlib: only for videos

        if self.env is None:
            self.env = make_eval_env(self.env_config, 1, self.hidden_dim, self.device, expose_beliefs=True)
        episode = rollout_greedy(self.env, policy, self.seed)
        return episode_rgb_frames(episode_frames(episode, self.env_config))

    def log(self, logger: Logger, run_dir: Path, policy: TensorDictModuleBase, step: int) -> Path:
        """Draw the episode and log it at ``step``; returns the GIF written into the run directory."""
        return log_video(logger, run_dir, "eval/video", self.frames(policy), step)
