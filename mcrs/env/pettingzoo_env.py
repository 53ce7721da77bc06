"""The MCRS environment as a PettingZoo ``ParallelEnv``, one episode at a time, agents ``uav_0 .. uav_{N-1}``.

It wraps :class:`~mcrs.env.core.MCRSCore` with ``num_envs=1``, so PettingZoo users and TorchRL training run
the same dynamics. Training uses the batched :class:`~mcrs.env.torchrl_env.MCRSEnv`; this adapter is for
interoperability and the one-environment throughput benchmark.

Per agent::

    observation   {"observation": float32 [obs_dim] in [-1, 1], "action_mask": int8 [8] (1 = allowed)}
    action        int in 0..7 (Discrete(8))
    reward        the team reward r1 + r2 + r3 + r4, the same for every agent
    termination   always False; episodes end by the time limit only
    truncation    True for every agent after max_steps steps, and agents is then emptied
    info          {"reading": bool (True = "F"), "position": (x, y), one float per running episode metric}

Infos hold numbers only, so that TorchRL's ``PettingZooWrapper`` stacks them into ``(group, "info",
name)``. ``state()`` is the global state (float32 ``[state_dim]``, paper eq. 22).
``render_mode="rgb_array"`` returns ``[H, W, 3]`` uint8 frames drawn by
:class:`mcrs.env.render.StateDrawing`; ``"human"`` shows them in a matplotlib window and needs a display.

TorchRL::

    from torchrl.envs.libs.pettingzoo import PettingZooWrapper
    env = PettingZooWrapper(MCRSParallelEnv("map10"), return_state=True, use_mask=False,
                            categorical_actions=True)
    # group "uav": ("uav", "observation", "observation") [4, 36], ("uav", "action_mask") [4, 8],
    # ("uav", "action") [4], ("uav", "info", <name>) [4], "state" [226]
"""

from __future__ import annotations

import os
import sys
from typing import Any, ClassVar

import numpy as np
import torch
from gymnasium import spaces
from pettingzoo import ParallelEnv

from mcrs.env.config import EnvConfig, scenario
from mcrs.env.core import N_ACTIONS, MCRSCore, StepResult
from mcrs.env.fusion import neighbour_graph
from mcrs.env.layout import StateLayout

AgentObs = dict[str, np.ndarray]


class MCRSParallelEnv(ParallelEnv[str, AgentObs, int]):
    """Multi-UAV reconnaissance and search with limited communication range, one episode at a time.

    Args:
        config: an :class:`EnvConfig` or a preset name (``"map10"``, ``"map15"``, ``"map20"``); its
            ``num_envs`` is replaced by 1.
        render_mode: ``None``, ``"rgb_array"`` or ``"human"``.
        **overrides: config fields to change, e.g. ``comm_range=3.0``.
    """

    metadata: ClassVar[dict[str, Any]] = {
        "name": "mcrs_v0",
        "render_modes": ["rgb_array", "human"],
        "render_fps": 5,
        "is_parallelizable": True,
    }

    def __init__(self, config: EnvConfig | str = "map10", render_mode: str | None = None, **overrides: Any):
        if isinstance(config, str):
            config = scenario(config, **overrides)
        elif overrides:
            config = config.replace(**overrides)
        if config.num_envs != 1:
            config = config.replace(num_envs=1)
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode={render_mode!r} is not supported: allowed {[None, *self.metadata['render_modes']]}"
            )
        if render_mode == "human":
            _check_display()
        self.render_mode = render_mode
        self._drawing: Any = None  # a StateDrawing, built on the first render
        self._window: Any = None  # the human mode's (figure, image)
        self._path: list[np.ndarray] = []  # positions since the reset (the trails)
        self._found: np.ndarray | None = None  # [W, H] cells whose m(F) reached tau so far
        self._last: StepResult | None = None
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
        """Start a new episode; the same ``seed`` replays the same episode."""
        if seed is not None:
            self.core.seed(seed)
        self.agents = list(self.possible_agents)
        self._path, self._found, self._drawing = [], None, None
        observations, infos, _ = self._convert(self.core.reset())
        if self.render_mode == "human":
            self.render()
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
        """Move every UAV by its action; ``agents`` empties after ``max_steps`` steps."""
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
        if self.render_mode == "human":
            self.render()
        return observations, rewards, terminations, truncations, infos

    def state(self) -> np.ndarray:
        """The global state: global m(U) and m(F) maps, UAV, no-fly and target positions (float32)."""
        if self._state is None:
            raise RuntimeError("state() is defined after reset()")
        return self._state

    def render(self) -> np.ndarray | None:
        """Return the current frame (``rgb_array``) or show it in a window (``human``); None without a render
        mode."""
        if self.render_mode is None:
            return None
        if self._last is None:
            raise RuntimeError("render() is defined after reset()")
        frame = self._frame()
        if self.render_mode == "rgb_array":
            return frame
        import matplotlib.pyplot as plt  # human mode only: an interactive backend and its window

        if self._window is None or not plt.fignum_exists(self._window[0].number):
            figure = plt.figure(f"MCRS {self.config.name}")
            axes = figure.add_axes((0, 0, 1, 1))
            axes.set_axis_off()
            self._window = (figure, axes.imshow(frame))
            plt.show(block=False)
        self._window[1].set_data(frame)
        plt.pause(1.0 / self.metadata["render_fps"])
        return None

    def close(self) -> None:
        """Close the human mode's window."""
        if self._window is not None:
            import matplotlib.pyplot as plt  # only the human mode opened a window

            plt.close(self._window[0])
            self._window = None

    # ------------------------------------------------------------------ internals
    def _convert(self, result: StepResult) -> tuple[dict[str, AgentObs], dict[str, dict[str, Any]], float]:
        """Split one core result into per-agent observations and infos, plus the team reward."""
        observation = result.observation[0].cpu().numpy()
        mask = result.action_mask[0].cpu().numpy().astype(np.int8)
        readings = result.reading[0].tolist()
        positions = result.position[0].tolist()
        self._state = result.state[0].cpu().numpy()
        metric_names = list(result.metrics)
        metric_values = torch.stack([result.metrics[name][0] for name in metric_names]).tolist()
        metrics = dict(zip(metric_names, metric_values, strict=True))
        self._last = result
        if self.render_mode is not None:  # what a frame shows besides the last result: paths, found cells
            self._path.append(np.asarray(positions, dtype=np.int64))
            found = result.state_map[0, 1].cpu().numpy() >= self.config.target_threshold
            self._found = found if self._found is None else self._found | found
        observations: dict[str, AgentObs] = {}
        infos: dict[str, dict[str, Any]] = {}
        for i, agent in enumerate(self.agents):
            observations[agent] = {"observation": observation[i], "action_mask": mask[i]}
            infos[agent] = {"reading": readings[i], "position": tuple(positions[i]), **metrics}
        return observations, infos, float(result.reward[0])

    def _frame(self) -> np.ndarray:
        """Draw the last result: the global m(U), the paths since the reset and this step's links."""
        from mcrs.env.render import StateDrawing, frame_title  # matplotlib, only when rendering

        result, cfg = self._last, self.config
        maps = result.state_map[0].cpu().numpy()
        if self._drawing is None:  # once per episode: no-fly cells and targets are the reset's
            layout = StateLayout.from_config(cfg)
            state = result.state[0]
            self._drawing = StateDrawing(
                cfg,
                layout.cells(state, layout.no_fly_position).cpu().numpy(),
                layout.cells(state, layout.target_position).cpu().numpy(),
            )
        neighbours = neighbour_graph(result.position[0], cfg.comm_range).cpu().numpy()
        reward = float(result.metrics["episode_reward"][0])
        title = frame_title(cfg, int(result.step_count[0]), maps[0], reward)
        return self._drawing.draw(maps[0], np.stack(self._path), neighbours, self._found, title)


def _check_display() -> None:
    """Refuse ``render_mode="human"`` without an interactive matplotlib backend or, on Linux, a display."""
    import matplotlib  # only for the human mode

    if sys.platform.startswith("linux") and not (
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    ):
        raise RuntimeError(
            'render_mode="human" needs a display (DISPLAY is not set); use render_mode="rgb_array" '
            "and save or show the frames yourself"
        )
    import matplotlib.pyplot as plt

    backend = plt.get_backend().lower()
    if backend in ("agg", "pdf", "ps", "svg", "cairo", "template") or "inline" in backend:
        raise RuntimeError(
            f'render_mode="human" needs an interactive matplotlib backend, and {matplotlib.get_backend()!r} '
            'is not one (set MPLBACKEND, e.g. TkAgg); or use render_mode="rgb_array"'
        )
