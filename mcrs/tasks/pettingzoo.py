"""Any PettingZoo ``ParallelEnv`` with discrete actions as a :class:`~mcrs.experiment.training.task.Task`.

In configs it is e.g. ``task=simple_spread``, in Python ``PettingZooTask("mpe2.simple_spread_v3", 25, {"N":
3})``. :class:`PettingZooBatchEnv` steps ``num_envs`` PettingZoo envs as one batched TorchRL ``EnvBase`` in
the experiment's key contract (docs/API.md, "Bring your own task"). Every agent must have the same spaces,
as a shared agent network needs. Keys (``E`` envs, ``N`` agents)::

    ("agents", "observation")   [E, N, obs]   float32, flattened; a dict's "observation" entry
    ("agents", "action_mask")   [E, N, A]     bool, a dict's "action_mask" entry, else all True
    "state"                     [E, *state]   env.state() if the env has one, else the observations joined
    "reward"                    [E, 1]        the agents' rewards summed (or mean)
    "terminated" / "truncated"  [E, 1]        every agent terminated or truncated, or max_steps reached

An agent that has left reads zeros with all actions allowed."""

from __future__ import annotations

import importlib
import math
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Binary, Composite, Unbounded
from torchrl.envs import EnvBase

from mcrs.experiment.training.task import Task
from mcrs.tasks.specs import done_spec, group_action_spec

GROUP = "agents"
REWARDS = ("sum", "mean")


def _factory(env: str) -> Any:
    """Return the callable ``env`` names: ``package.module`` (its ``parallel_env``) or
    ``package.module:callable``."""
    module_name, _, attribute = env.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as error:
        raise ValueError(f"task.env={env}: cannot import {module_name!r} ({error})") from None
    factory = getattr(module, attribute or "parallel_env", None)
    if not callable(factory):
        raise ValueError(
            f"task.env={env}: {module_name} has no {attribute or 'parallel_env'}(); name a module with "
            "parallel_env (mpe2.simple_spread_v3) or module:callable returning a ParallelEnv"
        )
    return factory


def _spaces(env: Any, spec: str) -> tuple[list[str], int, int, bool]:
    """Return the agents, the observation size, the number of actions and whether observations are dicts with
    an ``action_mask``. It refuses what one shared discrete agent cannot play."""
    agents = list(env.possible_agents)
    if not agents:
        raise ValueError(f"task.env={spec}: the env has no agents")
    sizes = set()
    for agent in agents:
        action, obs = env.action_space(agent), env.observation_space(agent)
        if not hasattr(action, "n") or getattr(action, "shape", ()) not in ((), None):
            raise ValueError(
                f"task.env={spec}: agent {agent}'s action space is {action}; PettingZooTask needs Discrete "
                "actions (an MPE env: continuous_actions=False)"
            )
        masked = hasattr(obs, "spaces") and "action_mask" in obs.spaces and "observation" in obs.spaces
        inner = obs.spaces["observation"] if masked else obs
        if getattr(inner, "shape", None) is None:
            raise ValueError(f"task.env={spec}: agent {agent}'s observation space {obs} is not an array")
        sizes.add((math.prod(inner.shape), int(action.n), masked))
    if len(sizes) != 1:
        raise ValueError(
            f"task.env={spec}: its agents' spaces differ ({sorted(sizes)}); one shared agent network needs "
            "the same observation size and actions for all"
        )
    obs_dim, n_actions, masked = sizes.pop()
    return agents, obs_dim, n_actions, masked


class PettingZooBatchEnv(EnvBase):
    """``num_envs`` PettingZoo parallel envs as one batched TorchRL env with the task contract's keys."""

    batch_locked = True

    def __init__(self, task: PettingZooTask, num_envs: int, device: torch.device | str = "cpu") -> None:
        super().__init__(device=device, batch_size=torch.Size([num_envs]))
        factory = _factory(task.env)
        self.envs = [factory(**task.env_kwargs) for _ in range(num_envs)]
        self.agents, self.obs_dim, self.n_actions, self.masked = _spaces(self.envs[0], task.env)
        self.task, self.max_steps = task, task.max_steps
        self.N, self._seed = len(self.agents), None
        E, N, A, dev = num_envs, self.N, self.n_actions, self.device
        self._steps = np.zeros(E, dtype=np.int64)
        self._obs = np.zeros((E, N, self.obs_dim), dtype=np.float32)
        self._mask = np.ones((E, N, A), dtype=bool)
        self._state = np.zeros((E, *task.state_shape), dtype=np.float32)
        self.observation_spec = Composite(
            {
                GROUP: Composite(
                    observation=Unbounded(shape=(E, N, self.obs_dim), dtype=torch.float32, device=dev),
                    action_mask=Binary(n=A, shape=(E, N, A), dtype=torch.bool, device=dev),
                    shape=(E, N),
                    device=dev,
                ),
                "state": Unbounded(shape=(E, *task.state_shape), dtype=torch.float32, device=dev),
            },
            shape=(E,),
            device=dev,
        )
        self.action_spec = group_action_spec(GROUP, E, N, A, dev)
        self.reward_spec = Composite(
            reward=Unbounded(shape=(E, 1), dtype=torch.float32, device=dev), shape=(E,), device=dev
        )
        self.done_spec = done_spec(E, dev)

    # ------------------------------------------------------------------ one env's arrays
    def _read(self, i: int, env: Any, observations: dict[str, Any]) -> None:
        """Copy env ``i``'s observations, masks and state into the batch arrays."""
        self._obs[i] = 0.0
        self._mask[i] = True
        for n, agent in enumerate(self.agents):
            if agent not in observations:
                continue
            value = observations[agent]
            if self.masked:
                self._mask[i, n] = np.asarray(value["action_mask"], dtype=bool).reshape(-1)
                value = value["observation"]
            self._obs[i, n] = np.asarray(value, dtype=np.float32).reshape(-1)
        if self.task.has_state:
            self._state[i] = np.asarray(env.state(), dtype=np.float32).reshape(self._state[i].shape)
        else:
            self._state[i] = self._obs[i].reshape(-1)

    def _out(self) -> dict[str, torch.Tensor]:
        dev = self.device
        return {
            "observation": torch.as_tensor(self._obs, device=dev).clone(),
            "action_mask": torch.as_tensor(self._mask, device=dev).clone(),
            "state": torch.as_tensor(self._state, device=dev).clone(),
        }

    def _tensordict(self, extra: dict[str, torch.Tensor]) -> TensorDict:
        out = self._out()
        E, N = self.batch_size[0], self.N
        agents = TensorDict(
            {"observation": out["observation"], "action_mask": out["action_mask"]},
            batch_size=[E, N],
            device=self.device,
        )
        return TensorDict({GROUP: agents, "state": out["state"], **extra}, batch_size=[E], device=self.device)

    # ------------------------------------------------------------------ EnvBase hooks
    def _set_seed(self, seed: int | None) -> None:
        """Make the next reset of env ``i`` ``reset(seed=seed + i)``."""
        self._seed = seed

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        E = self.batch_size[0]
        which = range(E)
        if tensordict is not None and "_reset" in tensordict.keys():  # noqa: SIM118
            which = tensordict.get("_reset").reshape(E).nonzero().flatten().tolist()
        for i in which:
            env = self.envs[i]
            observations, _ = env.reset(seed=None if self._seed is None else self._seed + i)
            self._steps[i] = 0
            self._read(i, env, observations)
        self._seed = None
        ended = torch.zeros(E, 1, dtype=torch.bool, device=self.device)
        return self._tensordict({"done": ended, "terminated": ended.clone(), "truncated": ended.clone()})

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        actions = tensordict.get((GROUP, "action")).cpu().numpy()  # [E, N]
        E = self.batch_size[0]
        reward = np.zeros(E, dtype=np.float32)
        terminated = np.zeros(E, dtype=bool)
        truncated = np.zeros(E, dtype=bool)
        for i, env in enumerate(self.envs):
            live = list(env.agents)
            step = {agent: int(actions[i, n]) for n, agent in enumerate(self.agents) if agent in live}
            observations, rewards, terms, truncs, _ = env.step(step)
            values = [float(rewards.get(agent, 0.0)) for agent in live]
            reward[i] = sum(values) / (len(self.agents) if self.task.reward == "mean" else 1)
            self._steps[i] += 1
            over = self._steps[i] >= self.max_steps
            finished = not env.agents or all(terms.get(a, False) or truncs.get(a, False) for a in live)
            truncated[i] = over or (finished and any(truncs.get(a, False) for a in live))
            terminated[i] = finished and not truncated[i]
            self._read(i, env, observations)
        dev = self.device
        term = torch.as_tensor(terminated, device=dev).unsqueeze(-1)
        trunc = torch.as_tensor(truncated, device=dev).unsqueeze(-1)
        return self._tensordict(
            {
                "reward": torch.as_tensor(reward, device=dev).unsqueeze(-1),
                "done": term | trunc,
                "terminated": term,
                "truncated": trunc,
            }
        )

    def close(self, *, raise_if_closed: bool = True) -> None:
        for env in self.envs:
            env.close()
        super().close(raise_if_closed=raise_if_closed)


class PettingZooTask(Task):
    """A PettingZoo ``ParallelEnv`` with discrete actions, a summed team reward and the state from ``state()``
    or the joined observations.

    Args:
        env: ``package.module`` with a ``parallel_env`` function (``mpe2.simple_spread_v3``), or
            ``package.module:callable`` returning a ``ParallelEnv``.
        max_steps: where episodes are truncated; the env's own limit (MPE's ``max_cycles``) or below.
        env_kwargs: keyword arguments of ``parallel_env``, e.g. ``{"N": 3}``.
        reward: ``sum`` (default) or ``mean`` of the agents' rewards.
        name: the task's name in logs and run directories; defaults to the module's last part.
    """

    group = GROUP

    def __init__(
        self,
        env: str = "mpe2.simple_spread_v3",
        max_steps: int = 25,
        env_kwargs: dict[str, Any] | None = None,
        reward: str = "sum",
        name: str | None = None,
    ) -> None:
        if not isinstance(env, str) or not env:
            raise ValueError(f"task.env={env!r}: a module with parallel_env (mpe2.simple_spread_v3)")
        if isinstance(max_steps, bool) or not isinstance(max_steps, int) or max_steps < 1:
            raise ValueError(f"task.max_steps={max_steps!r}: must be an integer >= 1")
        if env_kwargs is not None and not isinstance(env_kwargs, dict):
            raise ValueError(f"task.env_kwargs={env_kwargs!r}: a mapping of parallel_env's arguments")
        if reward not in REWARDS:
            raise ValueError(f"task.reward={reward!r}: allowed values are {', '.join(REWARDS)}")
        self.env, self.max_steps, self.reward = env, max_steps, reward
        self.env_kwargs = dict(env_kwargs or {})
        self.name = name or env.partition(":")[0].rsplit(".", 1)[-1].removesuffix("_v3")
        try:
            probe = _factory(env)(**self.env_kwargs)
        except TypeError as error:
            raise ValueError(f"task.env_kwargs: {error}") from None
        agents, self.obs_dim, self.n_actions, _ = _spaces(probe, env)
        self.n_agents = len(agents)
        probe.reset(seed=0)
        try:
            state = np.asarray(probe.state())
            self.has_state = True
            self.state_shape: tuple[int, ...] = tuple(int(s) for s in state.shape)
        except (NotImplementedError, AttributeError):
            self.has_state = False
            self.state_shape = (self.n_agents * self.obs_dim,)
        probe.close()

    def make_env(self, num_envs: int, device: torch.device) -> PettingZooBatchEnv:
        return PettingZooBatchEnv(self, num_envs, device)

    def settings(self) -> dict[str, Any]:
        return {
            "env": self.env,
            "max_steps": self.max_steps,
            "env_kwargs": dict(self.env_kwargs),
            "reward": self.reward,
            "name": self.name,
        }
