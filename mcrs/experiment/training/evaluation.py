"""Evaluation: episodes of a policy on separate, fixed-seed environments, and their metrics.

:func:`summarize` gives mean and std over episodes for every evaluation; the episodes come from one of two
runs: :func:`evaluate` (the trainer's greedy agent on any :class:`~mcrs.experiment.training.task.Task`) keeps the
whole rollout, because a task's metrics may need every step (the default sums the rewards);
:func:`final_metrics` (``mcrs-eval``'s heuristics and checkpoints on MCRS-LCR, whose metrics are running
totals) keeps only the last step, so nothing is stacked. The std convention is an explicit argument,
because both are in committed records: ``mcrs-eval`` (its tables, ``metrics.csv`` and the evaluation
records) takes the sample std (:data:`SAMPLE_STD`), the trainer's ``eval/episode_reward_std`` (the
training records' scalars) the population std (:data:`POPULATION_STD`)."""

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


SAMPLE_STD = 1  # std correction of mcrs-eval (n - 1): its tables, metrics.csv and evaluation records
POPULATION_STD = 0  # std correction of the trainer's eval/episode_reward_std (n), as training records hold it


@torch.no_grad()
def final_metrics(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase],
    seed: int | None,
    on_step: Callable[[], object] | None = None,
) -> dict[str, torch.Tensor]:
    """One episode in every environment of an MCRS ``env`` (seeded with ``seed`` first; None: the
    environments go on from where their generator stands), greedy actions; the final value of every
    metric per episode, ``{name: [E]}`` in float64 on the CPU whatever the env's device. ``on_step`` is
    called after every step (a progress bar's ``update``)."""
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
    """Mean and standard deviation over episodes in ``dtype``, the std with ``correction``
    (:data:`SAMPLE_STD` or :data:`POPULATION_STD`); 0 when there are no more episodes than the correction."""
    out = {}
    for name, v in values.items():
        v = v.to(dtype)
        std = v.std(correction=correction).item() if v.numel() > correction else 0.0
        out[name] = (v.mean().item(), std)
    return out


def evaluate(env: TransformedEnv, policy: TensorDictModuleBase, seed: int, task: Task) -> dict[str, float]:
    """Mean (and population std of the episode reward) of every metric of ``task`` over the batch of
    episodes, in float32 as the training records have always held them."""
    metrics = task.episode_metrics(rollout_greedy(env, policy, seed, task.max_steps))
    stats = summarize(metrics, correction=POPULATION_STD, dtype=torch.float32)
    out = {name: mean for name, (mean, _) in stats.items()}
    out["episode_reward_std"] = stats["episode_reward"][1]
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
