"""A task: what an :class:`~mcrs.experiment.trainer.Experiment` needs from an environment (BenchMARL's
``Task`` is the model).

The experiment builds every environment it uses (training, the collector's workers, evaluation) from the
task, reads the agents' and the mixer's sizes from it, points the loss and the acting policy at its keys and
logs the metrics it reports. :class:`MCRSTask` (the default, built from ``config.env``) is MCRS-LCR;
:class:`mcrs.tasks.matrix_game.MatrixGameTask` is a task we did not write. Bring your own by subclassing
:class:`Task` (docs/API.md, "Bring your own task")::

    Experiment(config, run_dir, task=MyTask()).run()

What a task's environment must be: a batched TorchRL ``EnvBase`` (``batch_size = [num_envs]``) with one
agent group, whose keys are (``E`` envs, ``N`` agents, ``A`` actions)::

    (group, "observation")   [E, N, obs_dim]   float32, every step
    (group, "action_mask")   [E, N, A]         bool, every step (all True if every action is always allowed)
    (group, "action")        [E, N]            int64, the action the experiment writes
    state_key                [E, *state_shape] float32, the mixer's global state, every step
    "reward"                 [E, 1]            the team's reward
    "done" / "terminated"    [E, 1]            every episode ends (done) at step ``max_steps`` exactly

Every episode lasts ``max_steps`` steps (a task whose episodes end earlier pads them to ``max_steps``):
the collector gathers whole episodes, ``[num_envs, max_steps]`` per batch. ``step_count`` is added with
TorchRL's ``StepCounter`` when the env has none; the agents' recurrent state is added by the experiment.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.envs import Compose, EnvBase, StepCounter, TransformedEnv

from mcrs.env.config import EnvConfig
from mcrs.env.core import METRICS, N_ACTIONS
from mcrs.env.torchrl_env import MCRSEnv
from mcrs.experiment.schema import Config, ConfigError
from mcrs.models.acting import recurrent_primer


class Task(ABC):
    """An environment the experiment can train and evaluate on.

    Subclasses set ``name`` and the sizes, and implement :meth:`make_env`; the keys default to the
    group ``"agents"`` and the state ``"state"``; :meth:`episode_metrics` defaults to the episode reward.
    A task must be picklable for ``train.collector=multiprocess`` (its workers build their environments
    from it).
    """

    name: str = "task"
    group: str = "agents"  #: the agent group: keys (group, "observation"), (group, "action_mask"), ...
    state_key: NestedKey = "state"  #: the mixer's global state
    has_maps: bool = False  #: MCRS belief maps: what the episodic memory's codec and logger.video draw on

    n_agents: int
    n_actions: int
    obs_dim: int
    state_shape: tuple[int, ...]
    max_steps: int  #: every episode's length: the collector gathers [num_envs, max_steps] per batch

    @abstractmethod
    def make_env(self, num_envs: int, device: torch.device) -> EnvBase:
        """``num_envs`` environments batched into one ``EnvBase`` on ``device``, seeded by ``set_seed``."""

    def episode_metrics(self, rollout: TensorDictBase) -> dict[str, torch.Tensor]:
        """Per-episode metrics ``{name: [E]}`` of whole episodes ``[E, max_steps]``; the experiment logs their
        means (``train/<name>``, ``eval/<name>``). Must hold ``episode_reward``. Default: the summed reward."""
        reward = rollout.get(("next", "reward")).float()
        return {"episode_reward": reward.reshape(*rollout.batch_size, -1).sum(-1).sum(-1)}

    def fingerprint(self) -> dict[str, Any]:
        """What identifies the task in a checkpoint (a resume on another task is refused): plain values.
        A checkpoint written before tasks has none of these fields and resumes as MCRS."""
        return {"task.name": self.name, "task.class": f"{type(self).__module__}.{type(self).__qualname__}"}

    # ------------------------------------------------------------------ derived: keys
    @property
    def observation_key(self) -> NestedKey:
        return (self.group, "observation")

    @property
    def action_key(self) -> NestedKey:
        return (self.group, "action")

    @property
    def action_mask_key(self) -> NestedKey:
        return (self.group, "action_mask")

    @property
    def step_keys(self) -> tuple[NestedKey, ...]:
        """What the replay keeps at every step (:func:`~mcrs.experiment.replay.episodes_from_rollout`)."""
        return (self.observation_key, self.action_mask_key, self.state_key)

    def loss_keys(self) -> dict[str, NestedKey]:
        """``ValueFactorisationLoss.set_keys(**task.loss_keys())``."""
        return {
            "observation": self.observation_key,
            "action": self.action_key,
            "action_mask": self.action_mask_key,
            "state": self.state_key,
        }


class MCRSTask(Task):
    """MCRS-LCR on one map: the experiment's default task, built from ``config.env`` (the env section of the
    config is in every checkpoint's fingerprint; the task adds its name and class)."""

    has_maps = True

    def __init__(self, env_config: EnvConfig) -> None:
        self.env_config = env_config
        self.name = env_config.name
        self.n_agents, self.n_actions, self.obs_dim = env_config.n_uavs, N_ACTIONS, env_config.obs_dim
        self.state_shape, self.max_steps = (env_config.state_dim,), env_config.max_steps

    def make_env(self, num_envs: int, device: torch.device, expose_beliefs: bool | None = None) -> MCRSEnv:
        """``expose_beliefs``: also write what an episode's pictures are drawn from (None: as configured)."""
        overrides: dict[str, Any] = {"num_envs": num_envs}
        if expose_beliefs is not None:
            overrides["expose_beliefs"] = expose_beliefs
        return MCRSEnv(self.env_config.replace(**overrides), device=str(device))

    def episode_metrics(self, rollout: TensorDictBase) -> dict[str, torch.Tensor]:
        """The env's running metrics (``mcrs.env.core.METRICS``) at each episode's last step."""
        return {name: rollout.get(("next", "metrics", name))[:, -1].float() for name in METRICS}


def as_task(task: Task | EnvConfig) -> Task:
    """A task; an :class:`EnvConfig` (what the builders took before tasks) is its :class:`MCRSTask`."""
    return MCRSTask(task) if isinstance(task, EnvConfig) else task


def with_agent_state(env: EnvBase, task: Task, num_envs: int, hidden_dim: int, device) -> TransformedEnv:
    """``env`` with what the recurrent acting policy reads: ``step_count`` (TorchRL's ``StepCounter``, when
    the env writes none) and the agents' carried state (:func:`~mcrs.models.acting.recurrent_primer`)."""
    primer = recurrent_primer(num_envs, task.n_agents, hidden_dim, group=task.group, device=device)
    if "step_count" in env.observation_spec:
        return TransformedEnv(env, primer)
    return TransformedEnv(env, Compose(StepCounter(), primer))


def check_env(task: Task, env: EnvBase) -> None:
    """Raise :class:`ConfigError` where ``env``'s specs disagree with the sizes and keys ``task`` declares
    (``obs_dim``, ``n_agents``, ``n_actions``, ``state_shape``), naming the attribute and the env's value:
    the networks are built from the declared sizes, so a mismatch would surface as a shape error deep in
    torch."""
    spec = env.observation_spec
    problems = []
    expected = {
        task.observation_key: ("n_agents, obs_dim", (task.n_agents, task.obs_dim)),
        task.action_mask_key: ("n_agents, n_actions", (task.n_agents, task.n_actions)),
        task.state_key: ("state_shape", tuple(task.state_shape)),
    }
    for key, (attributes, sizes) in expected.items():
        if key not in spec.keys(include_nested=True):
            problems.append(f"its env has no observation key {key!r}, which the experiment reads every step")
            continue
        shape = tuple(spec[key].shape[len(env.batch_size) :])
        if shape != sizes:
            problems.append(f"{attributes} = {sizes}, but its env's {key!r} is {shape} per env")
    if problems:
        raise ConfigError(f"task {task.name!r} ({type(task).__name__}): " + "; ".join(problems))


def check_supported(config: Config, task: Task) -> None:
    """Raise :class:`ConfigError` naming every setting of ``config`` that ``task`` cannot run."""
    problems = unsupported(config, task)
    if problems:
        raise ConfigError(f"invalid config for task {task.name!r}:\n  - " + "\n  - ".join(problems))


def unsupported(config: Config, task: Task) -> list[str]:
    """The settings of ``config`` that ``task`` cannot run, one line each (none: it can)."""
    problems = []
    if not task.has_maps:
        if config.algo.memory.enabled:
            problems.append(
                f"algo.memory.enabled: the episodic memory encodes MCRS belief maps and task {task.name!r} "
                f"has none (algo={config.algo.name}); use an algorithm without it (qmix, vdn, qplex)"
            )
        if config.logger.video:
            problems.append(f"logger.video: draws MCRS belief maps and task {task.name!r} has none")
    if config.algo.curiosity_scale > 0 and (task.group, task.state_key) != ("agents", "state"):
        problems.append(
            f"algo.curiosity_scale: EMC's curiosity reads the group 'agents' and the state 'state'; task "
            f"{task.name!r} has group {task.group!r} and state {task.state_key!r}"
        )
    if str(config.train.collector) == "multiprocess":
        import pickle

        try:
            pickle.dumps(task)
        except Exception as error:  # what pickle raises depends on the object
            problems.append(
                f"train.collector=multiprocess: the workers build their environments from the task, and "
                f"task {task.name!r} cannot be pickled ({type(error).__name__}: {error}); "
                "use train.collector=single"
            )
    return problems
