"""Evaluation: episodes of a policy on separate, fixed-seed environments, and their metrics.

:func:`evaluate` keeps the trainer's whole greedy rollout, since a task's metrics may need every step;
:func:`final_metrics` keeps only the last step of MCRS-LCR's running totals, for ``mcrs-eval``. Records hold
both std conventions: ``mcrs-eval`` the sample std (:data:`SAMPLE_STD`), the trainer's
``eval/episode_reward_std`` the population std (:data:`POPULATION_STD`).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.record.loggers import Logger

from mcrs.env.config import EnvConfig
from mcrs.env.core import METRICS
from mcrs.experiment.run.logging import log_video
from mcrs.experiment.training.task import MCRSTask, Task, as_task, with_agent_state


def make_eval_env(
    env_config: EnvConfig | Task,
    episodes: int,
    hidden_dim: int,
    device: str | torch.device,
    expose_beliefs: bool = False,
) -> TransformedEnv:
    """``episodes`` environments of the task as one batch, carrying the agents' recurrent state;
    ``expose_beliefs`` (MCRS only) also writes what pictures are drawn from."""
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
    """One greedy episode ``[E, T]`` in every environment of ``env`` from ``seed``; ``max_steps`` defaults to
    the MCRS env's."""
    env.set_seed(seed)
    steps = env.base_env.config.max_steps if max_steps is None else max_steps
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        return env.rollout(steps, policy, break_when_any_done=False)


SAMPLE_STD = 1  # std correction of mcrs-eval (n - 1): its tables, metrics.csv and evaluation records
POPULATION_STD = 0  # std correction of the trainer's eval/episode_reward_std (n), as training records hold it


@torch.no_grad()
def final_metrics(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase],
    seed: int | None,
    on_step: Callable[[], object] | None = None,
) -> dict[str, torch.Tensor]:
    """The final value of every metric after one greedy episode in every environment of an MCRS ``env``,
    ``{name: [E]}`` in float64 on the CPU. ``seed`` None lets the environments go on from where their
    generator stands; ``on_step`` is called after every step."""
    if seed is not None:
        env.set_seed(seed)
    steps = getattr(env, "base_env", env).config.max_steps
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.reset()
        for _ in range(steps):
            td = env.step(policy(td))["next"]
            if on_step is not None:
                on_step()
    metrics = td.get("metrics")  # copied: a CPU env reuses its buffers
    return {name: metrics.get(name).to(device="cpu", dtype=torch.float64, copy=True) for name in METRICS}


def summarize(
    values: dict[str, torch.Tensor], correction: int, dtype: torch.dtype = torch.float64
) -> dict[str, tuple[float, float]]:
    """Mean and standard deviation over episodes in ``dtype``, the std with ``correction`` and 0 when there
    are no more episodes than the correction."""
    out = {}
    for name, v in values.items():
        v = v.to(dtype)
        std = v.std(correction=correction).item() if v.numel() > correction else 0.0
        out[name] = (v.mean().item(), std)
    return out


def evaluate(env: TransformedEnv, policy: TensorDictModuleBase, seed: int, task: Task) -> dict[str, float]:
    """Mean of every metric of ``task`` over the batch of episodes, and the episode reward's population std,
    in float32 as the training records hold them."""
    metrics = task.episode_metrics(rollout_greedy(env, policy, seed, task.max_steps))
    stats = summarize(metrics, correction=POPULATION_STD, dtype=torch.float32)
    out = {name: mean for name, (mean, _) in stats.items()}
    out["episode_reward_std"] = stats["episode_reward"][1]
    return out


class EvaluationVideo:
    """``logger.video``: one greedy episode (the first evaluation seed, one environment with its beliefs
    exposed) drawn as the episode GIF is and logged as ``eval/video``."""

    def __init__(self, env_config: EnvConfig, hidden_dim: int, device: torch.device, seed: int) -> None:
        self.env_config, self.hidden_dim, self.device, self.seed = env_config, hidden_dim, device, seed
        self.env: TransformedEnv | None = None  # built on the first video

    def frames(self, policy: TensorDictModuleBase) -> list[np.ndarray]:
        """``[H, W, 3]`` uint8 frames of an episode run to the time limit."""
        from mcrs.env.render import episode_frames, episode_rgb_frames  # matplotlib: only for videos

        if self.env is None:
            self.env = make_eval_env(self.env_config, 1, self.hidden_dim, self.device, expose_beliefs=True)
        episode = rollout_greedy(self.env, policy, self.seed)
        return episode_rgb_frames(episode_frames(episode, self.env_config))

    def log(self, logger: Logger, run_dir: Path, policy: TensorDictModuleBase, step: int) -> Path:
        """Draw the episode and log it at ``step``; returns the GIF written into the run directory."""
        return log_video(logger, run_dir, "eval/video", self.frames(policy), step)
