"""The MCRS-LCR environment as a PettingZoo ``ParallelEnv``: one episode, agents ``uav_0 .. uav_{N-1}``.

A thin adapter over :class:`~mcrs.env.core.MCRSCore` with ``num_envs=1``, so that PettingZoo users and the
TorchRL training path run exactly the same dynamics (no second implementation to drift). It exists for
interoperability and as the "one environment at a time" reference of the throughput benchmark; training
uses the batched :class:`~mcrs.env.torchrl_env.MCRSEnv`.

Per agent::

    observation   {"observation": float32 [obs_dim] in [-1, 1], "action_mask": int8 [8] (1 = allowed)}
    action        int in 0..7 (``Discrete(8)``)
    reward        the team reward r1 + r2 + r3 + r4 (the same for every agent)
    termination   always False (episodes end by the time limit only)
    truncation    True for every agent after ``max_steps`` steps; ``agents`` is then emptied
    info          {"metrics": {name: float} (running episode metrics), "reading": bool (True = "F"),
                   "position": (x, y)}

``state()`` is the global state (float32 ``[state_dim]``, paper eq. 22).
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch
from gymnasium import spaces
from pettingzoo import ParallelEnv

from mcrs.env.config import EnvConfig, scenario
from mcrs.env.core import N_ACTIONS, MCRSCore, StepResult

AgentObs = dict[str, np.ndarray]


class MCRSParallelEnv(ParallelEnv[str, AgentObs, int]):
    """Multi-UAV reconnaissance and search with limited communication range, one episode at a time.

    Args:
        config: a validated :class:`EnvConfig`, or a preset name (``"map10"``, ``"map15"``, ``"map20"``).
            Its ``num_envs`` is replaced by 1.
        render_mode: only ``None``; episodes are drawn by ``mcrs-render`` from the exposed beliefs.
        **overrides: config fields to change, e.g. ``invalid_action="clip"``, ``comm_range=3.0``.
    """

    metadata: ClassVar[dict[str, Any]] = {"name": "mcrs_v0", "render_modes": [], "is_parallelizable": True}

    def __init__(self, config: EnvConfig | str = "map10", render_mode: str | None = None, **overrides: Any):
        if isinstance(config, str):
            config = scenario(config, **overrides)
        elif overrides:
            config = config.replace(**overrides)
        if config.num_envs != 1:
            config = config.replace(num_envs=1)
        if render_mode is not None:
            raise ValueError(
                f"render_mode={render_mode!r} is not supported: allowed {self.metadata['render_modes'] + [None]}"
            )
        self.render_mode = render_mode
        self.config = config
        self.core = MCRSCore(config)
        self.possible_agents = [f"uav_{i}" for i in range(config.n_uavs)]
        self.agents: list[str] = []
        # One space object per agent, returned as is (PettingZoo requires the same object every call).
        self.observation_spaces = {
            agent: spaces.Dict(
                {
                    "observation": spaces.Box(-1.0, 1.0, shape=(config.obs_dim,), dtype=np.float32),
                    "action_mask": spaces.Box(0, 1, shape=(N_ACTIONS,), dtype=np.int8),
                }
            )
            for agent in self.possible_agents
        }
        self.action_spaces = {agent: spaces.Discrete(N_ACTIONS) for agent in self.possible_agents}
        self.state_space = spaces.Box(-1.0, 1.0, shape=(config.state_dim,), dtype=np.float32)
        self._state: np.ndarray | None = None

    # ------------------------------------------------------------------ spaces
    def observation_space(self, agent: str) -> spaces.Dict:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Discrete:
        return self.action_spaces[agent]

    # ------------------------------------------------------------------ PettingZoo API
    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, AgentObs], dict[str, dict[str, Any]]]:
        """Start a new episode; ``seed`` reseeds the core, so the same seed replays the same episode."""
        if seed is not None:
            self.core.seed(seed)
        self.agents = list(self.possible_agents)
        observations, infos, _ = self._convert(self.core.reset())
        return observations, infos

    def step(
        self, actions: dict[str, int]
    ) -> tuple[
        dict[str, AgentObs],
        dict[str, float],
        dict[str, bool],
        dict[str, bool],
        dict[str, dict[str, Any]],
    ]:
        """Move every UAV by its action; the episode ends (``agents`` empties) after ``max_steps`` steps."""
        if not self.agents:
            raise RuntimeError("the episode is over (or never started): call reset() before step()")
        missing = [agent for agent in self.agents if agent not in actions]
        if missing:
            raise ValueError(f"actions is missing agent(s) {missing}; every live agent must act each step")
        unknown = [agent for agent in actions if agent not in self.observation_spaces]
        if unknown:
            raise ValueError(f"actions names unknown agent(s) {unknown}; agents are {self.possible_agents}")
        action = np.asarray([actions[agent] for agent in self.possible_agents])
        if action.dtype.kind not in "iu" or action.shape != (len(self.possible_agents),):
            raise TypeError(
                f"each action must be one integer in 0..{N_ACTIONS - 1}; got {[actions[a] for a in self.agents]}"
            )
        result = self.core.step(torch.from_numpy(action.astype(np.int64, copy=False)).unsqueeze(0))
        observations, infos, reward = self._convert(result)
        done = bool(result.truncated[0])
        agents = self.agents
        rewards = dict.fromkeys(agents, reward)
        terminations = dict.fromkeys(agents, False)
        truncations = dict.fromkeys(agents, done)
        if done:
            self.agents = []
        return observations, rewards, terminations, truncations, infos

    def state(self) -> np.ndarray:
        """The global state: global m(U) and m(F) maps, UAV, no-fly and target positions (float32)."""
        if self._state is None:
            raise RuntimeError("state() is defined after reset()")
        return self._state

    def render(self) -> None:
        """Nothing to render in-process (``render_mode`` is always None); see ``mcrs-render``."""
        return None

    def close(self) -> None:
        """Nothing to release: the core holds only tensors."""

    # ------------------------------------------------------------------ internals
    def _convert(self, result: StepResult) -> tuple[dict[str, AgentObs], dict[str, dict[str, Any]], float]:
        """Per-agent dicts from one core result: one ``.numpy()`` per tensor, then views per agent."""
        observation = result.observation[0].cpu().numpy()
        mask = result.action_mask[0].cpu().numpy().astype(np.int8)
        readings = result.reading[0].tolist()
        positions = result.position[0].tolist()
        self._state = result.state[0].cpu().numpy()
        metric_names = list(result.metrics)
        metric_values = torch.stack([result.metrics[name][0] for name in metric_names]).tolist()
        metrics = dict(zip(metric_names, metric_values, strict=True))
        observations: dict[str, AgentObs] = {}
        infos: dict[str, dict[str, Any]] = {}
        for i, agent in enumerate(self.agents):
            observations[agent] = {"observation": observation[i], "action_mask": mask[i]}
            infos[agent] = {"metrics": dict(metrics), "reading": readings[i], "position": tuple(positions[i])}
        return observations, infos, float(result.reward[0])
