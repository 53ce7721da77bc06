"""One episode as arrays: the rollout (beliefs exposed) and its per-step numpy frames.

Every picture of :mod:`mcrs.viz` is drawn from these, so a rollout is taken once and drawn many times.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from tensordict import TensorDictBase

from mcrs.env.config import EnvConfig
from mcrs.env.layout import StateLayout
from mcrs.env.torchrl_env import MCRSEnv
from mcrs.policies import make_policy


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


def rollout_comm_pair(
    env_config: EnvConfig, policy_name: str, seed: int
) -> tuple[TensorDictBase, TensorDictBase]:
    """The same episode seed with the config's communication and without any (``comm_range=0``)."""
    with_comm = rollout_episode(env_config, policy_name, seed)
    without = rollout_episode(env_config.replace(comm_range=0.0), policy_name, seed)
    return with_comm, without
