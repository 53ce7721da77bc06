"""VMAS scenarios with discrete actions as a :class:`~mcrs.experiment.training.task.Task`
(``task=vmas_navigation``).

VMAS (``pip install "mcrs[vmas]"``) steps all ``num_envs`` environments as batched tensors through
TorchRL's ``VmasEnv``. :class:`VmasTask` fits it to the experiment's key contract (docs/API.md, "Bring your
own task") with :class:`TeamKeys` and TorchRL's ``StepCounter``::

    ("agents", "observation")   [E, N, obs]   VMAS's own, every agent in one group
    ("agents", "action_mask")   [E, N, A]     all True
    "state"                     [E, N * obs]  the observations joined; VMAS has no global state
    "reward"                    [E, 1]        the agents' rewards summed
    "terminated"                [E, 1]        the scenario's own end (navigation: every agent on its goal)
    "truncated"                 [E, 1]        max_steps reached

Episodes that end early are padded and masked in the replay and the loss. VMAS draws from torch's global
generator, which ``set_seed`` seeds, so runs are reproducible."""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.data import Binary, Composite, Unbounded
from torchrl.envs import Compose, EnvBase, StepCounter, TransformedEnv
from torchrl.envs.transforms import Transform
from torchrl.envs.utils import MarlGroupMapType

from mcrs.experiment.training.task import Task, first_episode_sum

GROUP = "agents"


class TeamKeys(Transform):
    """Add the task contract's keys to a VMAS env, batched: an all-True action mask, the joined observations
    as ``state`` and the summed reward."""

    def __init__(self, n_actions: int, group: str = GROUP) -> None:
        super().__init__(in_keys=[], out_keys=[])
        self.n_actions, self.group = n_actions, group

    def _keys(self, td: TensorDictBase) -> TensorDictBase:
        obs = td.get((self.group, "observation"))  # [E, N, obs]
        td.set(
            (self.group, "action_mask"),
            torch.ones(*obs.shape[:-1], self.n_actions, dtype=torch.bool, device=obs.device),
        )
        td.set("state", obs.flatten(-2))
        return td

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        next_tensordict = self._keys(next_tensordict)
        reward = next_tensordict.get((self.group, "reward"), None)  # [E, N, 1]
        if reward is not None:
            next_tensordict.set("reward", reward.sum(-2))
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._keys(tensordict_reset)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        group = observation_spec[self.group]
        obs = group["observation"]
        *lead, n_agents, obs_dim = obs.shape
        group["action_mask"] = Binary(
            n=self.n_actions, shape=(*lead, n_agents, self.n_actions), dtype=torch.bool, device=obs.device
        )
        observation_spec["state"] = Unbounded(
            shape=(*lead, n_agents * obs_dim), dtype=obs.dtype, device=obs.device
        )
        return observation_spec

    def transform_reward_spec(self, reward_spec: Composite) -> Composite:
        agents = reward_spec[self.group, "reward"]
        reward_spec["reward"] = Unbounded(
            shape=(*agents.shape[:-2], 1), dtype=agents.dtype, device=agents.device
        )
        return reward_spec


class VmasTask(Task):
    """A VMAS scenario with discrete actions, e.g. ``VmasTask("navigation", 50, {"n_agents": 3})``.

    Args:
        scenario: a VMAS scenario name, e.g. ``navigation``, ``balance``, ``transport``.
        max_steps: where ``StepCounter`` truncates episodes.
        scenario_kwargs: the scenario's own settings (``n_agents``, ``collisions``, ``shared_rew``, ...).
        name: the task's name in logs and run directories; defaults to ``vmas_<scenario>``.
    """

    group = GROUP

    def __init__(
        self,
        scenario: str = "navigation",
        max_steps: int = 100,
        scenario_kwargs: dict[str, Any] | None = None,
        name: str | None = None,
    ) -> None:
        if not isinstance(scenario, str) or not scenario:
            raise ValueError(f"task.scenario={scenario!r}: a VMAS scenario name (navigation, balance, ...)")
        if isinstance(max_steps, bool) or not isinstance(max_steps, int) or max_steps < 1:
            raise ValueError(f"task.max_steps={max_steps!r}: must be an integer >= 1")
        if scenario_kwargs is not None and not isinstance(scenario_kwargs, dict):
            raise ValueError(
                f"task.scenario_kwargs={scenario_kwargs!r}: a mapping of the scenario's settings"
            )
        self.scenario, self.max_steps = scenario, max_steps
        self.scenario_kwargs = dict(scenario_kwargs or {})
        self.name = name or f"vmas_{scenario}"
        probe = self._vmas(1, torch.device("cpu"))  # the sizes, from the scenario itself
        action = probe.full_action_spec[GROUP, "action"]
        if not hasattr(action.space, "n"):
            raise ValueError(f"task.scenario={scenario}: its actions are not discrete")
        self.n_agents, self.n_actions = int(action.shape[-1]), int(action.space.n)
        self.obs_dim = int(probe.observation_spec[GROUP, "observation"].shape[-1])
        self.state_shape = (self.n_agents * self.obs_dim,)
        probe.close()

    def _vmas(self, num_envs: int, device: torch.device) -> EnvBase:
        try:
            from torchrl.envs.libs.vmas import VmasEnv  # needs the optional vmas package
        except ImportError as error:  # pragma: no cover - the vmas extra is missing
            raise ValueError(f"task {self.name}: needs VMAS: pip install 'mcrs[vmas]' ({error})") from None
        try:
            return VmasEnv(
                self.scenario,
                num_envs=num_envs,
                continuous_actions=False,
                max_steps=None,  # the time limit is StepCounter's: truncated, not terminated
                device=device,
                group_map=MarlGroupMapType.ALL_IN_ONE_GROUP,
                **self.scenario_kwargs,
            )
        except (ImportError, AttributeError, ModuleNotFoundError) as error:
            raise ValueError(f"task.scenario={self.scenario}: not a VMAS scenario ({error})") from None
        except TypeError as error:
            raise ValueError(f"task.scenario_kwargs: {error}") from None

    def make_env(self, num_envs: int, device: torch.device) -> TransformedEnv:
        return TransformedEnv(
            self._vmas(num_envs, device), Compose(StepCounter(self.max_steps), TeamKeys(self.n_actions))
        )

    def settings(self) -> dict[str, Any]:
        return {
            "scenario": self.scenario,
            "max_steps": self.max_steps,
            "scenario_kwargs": dict(self.scenario_kwargs),
            "name": self.name,
        }

    def episode_metrics(self, rollout: TensorDictBase) -> dict[str, torch.Tensor]:
        """Return the team's return and the length of each row's first episode, shorter when the goal is
        reached."""
        E, T = rollout.batch_size
        done = rollout.get(("next", "done")).reshape(E, T).long()
        length = ((done.cumsum(-1) - done) == 0).sum(-1).float()
        return {"episode_reward": first_episode_sum(rollout, ("next", "reward")), "episode_length": length}
