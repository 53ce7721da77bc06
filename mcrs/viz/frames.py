"""One episode as arrays: the rollout with beliefs exposed, and its per-step numpy frames.

Every picture of :mod:`mcrs.viz` is drawn from these, so a rollout is taken once. :class:`EpisodeFrames`
lives in mcrs.env.render, beside the drawing that ``render()`` and the evaluation video share."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from mcrs.env.config import EnvConfig
from mcrs.env.render import EpisodeFrames, episode_frames
from mcrs.env.torchrl_env import MCRSEnv
from mcrs.policies import make_policy, policy_env

__all__ = ["EpisodeFrames", "episode_frames", "rollout_comm_pair", "rollout_episode"]


def rollout_episode(env_config: EnvConfig, policy_name: str, seed: int) -> TensorDictBase:
    """Roll out one full episode in one env with beliefs exposed; return a ``[1, T]`` tensordict."""
    cfg = policy_env(policy_name, env_config.replace(num_envs=1, expose_beliefs=True))
    env = MCRSEnv(cfg)
    env.set_seed(seed)
    policy = make_policy(policy_name, cfg, seed)
    with torch.no_grad():
        return env.rollout(cfg.max_steps, policy, break_when_any_done=False)


def rollout_comm_pair(
    env_config: EnvConfig, policy_name: str, seed: int
) -> tuple[TensorDictBase, TensorDictBase]:
    """Roll out the same episode seed with the config's communication and with ``comm_range=0``."""
    with_comm = rollout_episode(env_config, policy_name, seed)
    without = rollout_episode(env_config.replace(comm_range=0.0), policy_name, seed)
    return with_comm, without
