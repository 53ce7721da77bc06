"""A task: what an :class:`~mcrs.experiment.training.trainer.Experiment` needs from an environment, modelled
on BenchMARL's ``Task``.

The experiment builds its environments from the task, sizes the networks from it and reads its keys and
metrics. :class:`MCRSTask`, built from ``config.env``, is the default; bring your own by subclassing
:class:`Task` (docs/API.md, "Bring your own task")::

    Experiment(config, run_dir, task=MyTask()).run()

A task's environment is a batched TorchRL ``EnvBase`` (``batch_size = [num_envs]``) with one agent group.
These are the keys the experiment reads (``E`` envs, ``N`` agents, ``A`` actions); :func:`check_env` checks
them against the env's specs before anything runs::

    (group, "observation")   [E, N, obs_dim]     float, at reset and every step
    (group, "action_mask")   [E, N, A]           bool, at reset and every step (all True: every action allowed)
    (group, "action")        [E, N]              int64 in 0..A-1 (action spec): what the experiment writes
    state_key                [E, *state_shape]   float, the mixer's global state, at reset and every step
    "reward"                 [E, 1]              float, the team's reward of the step
    "done"                   [E, 1]              bool: the episode ended at this step (terminated or truncated)
    "terminated"             [E, 1]              bool: it ended by the task (a goal, a failure): no bootstrap
    "truncated"              [E, 1]              bool: it ended by the time limit (the step ``max_steps``)

Every episode ends by step ``max_steps``; ``algo.time_limit`` says whether a truncated step is terminal (the
default) or bootstraps. The collector gathers ``[num_envs, max_steps]`` steps per batch, each row from a
reset, and keeps each row's first episode, padded and masked as pymarl does.
"""

from __future__ import annotations

import importlib
import inspect
import pickle
from abc import ABC, abstractmethod
from collections.abc import Mapping
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.envs import Compose, EnvBase, StepCounter, TransformedEnv

from mcrs.env.config import EnvConfig
from mcrs.env.core import METRICS, N_ACTIONS
from mcrs.env.torchrl_env import MCRSEnv
from mcrs.experiment.run.history import class_path
from mcrs.experiment.schema import Config, ConfigError
from mcrs.models.acting import recurrent_primer


class Task(ABC):
    """An environment the experiment can train and evaluate on. Subclasses set ``name`` and the sizes and
    implement :meth:`make_env`; one whose constructor takes arguments returns them from :meth:`settings`, so
    its runs can be rebuilt. It must be picklable for ``train.collector=multiprocess``."""

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
        """Per-episode metrics ``{name: [E]}`` of a rollout's rows ``[E, max_steps]``, which must include
        ``episode_reward``; the experiment logs their means. Default: the reward summed over each row's first
        episode."""
        return {"episode_reward": first_episode_sum(rollout, ("next", "reward"))}

    def settings(self) -> dict[str, Any]:
        """The keyword arguments that rebuild this task, as plain values that ``config.yaml`` can keep."""
        return {}

    def spec(self) -> dict[str, Any]:
        """How to rebuild the task, ``{"_target_": "<module>.<class>", **settings()}``: the config's ``task``
        node."""
        return {TARGET: f"{type(self).__module__}.{type(self).__qualname__}", **self.settings()}

    def fingerprint(self) -> dict[str, Any]:
        """What identifies the task in a checkpoint, so that a resume on another task is refused; the settings
        are in the config's ``task`` node."""
        return {"task.name": self.name, "task.class": class_path(type(self))}

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
        """What the replay keeps at every step."""
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
    """MCRS-LCR on one map, built from ``config.env``: the experiment's default task."""

    has_maps = True

    def __init__(self, env_config: EnvConfig) -> None:
        self.env_config = env_config
        self.name = env_config.name
        self.n_agents, self.n_actions, self.obs_dim = env_config.n_uavs, N_ACTIONS, env_config.obs_dim
        self.state_shape, self.max_steps = (env_config.state_dim,), env_config.max_steps

    def make_env(self, num_envs: int, device: torch.device, expose_beliefs: bool | None = None) -> MCRSEnv:
        """``expose_beliefs`` also writes what an episode's pictures are drawn from (None: as configured)."""
        overrides: dict[str, Any] = {"num_envs": num_envs}
        if expose_beliefs is not None:
            overrides["expose_beliefs"] = expose_beliefs
        return MCRSEnv(self.env_config.replace(**overrides), device=str(device))

    def episode_metrics(self, rollout: TensorDictBase) -> dict[str, torch.Tensor]:
        """The env's running metrics (``mcrs.env.core.METRICS``) at each episode's last step."""
        return {name: rollout.get(("next", "metrics", name))[:, -1].float() for name in METRICS}


#: The key of a task node that names its class (Hydra's spelling).
TARGET = "_target_"


def first_episode_sum(rollout: TensorDictBase, key: NestedKey) -> torch.Tensor:
    """``key`` (``[E, T, ...]``) summed over each row's first episode, up to and including its first done;
    ``[E]`` float32."""
    E, T = rollout.batch_size
    value = rollout.get(key).float().reshape(E, T, -1).sum(-1)
    done = rollout.get(("next", "done")).reshape(E, T, -1).any(-1).long()
    return (value * ((done.cumsum(-1) - done) == 0)).sum(-1)


def make_task(node: Mapping[str, Any] | Task) -> Task:
    """The task a ``task`` node (``{"_target_": "pkg.module.Class", **settings}``) describes; a :class:`Task`
    is returned as it is. Anything but an importable :class:`Task` subclass and its constructor's arguments is
    a :class:`ConfigError` naming ``task.<key>``."""
    if isinstance(node, Task):
        return node
    if not isinstance(node, Mapping) or not isinstance(node.get(TARGET), str):
        raise ConfigError(
            f"task: expected a node with {TARGET} (an importable Task class, 'package.module.Class') and its "
            f"settings, got {node!r:.120}"
        )
    target, settings = str(node[TARGET]), {str(k): v for k, v in node.items() if k != TARGET}
    module_name, _, class_name = target.rpartition(".")
    try:
        cls = getattr(importlib.import_module(module_name), class_name) if module_name else None
    except ImportError as error:
        raise ConfigError(
            f"task.{TARGET}={target}: cannot import {module_name!r} ({error}); a task defined in a script "
            "(__main__) or a test file is rebuilt only where its module is importable (PYTHONPATH)"
        ) from None
    except AttributeError:
        cls = None
    if not (isinstance(cls, type) and issubclass(cls, Task)) or inspect.isabstract(cls):
        raise ConfigError(f"task.{TARGET}={target}: not a Task class (a subclass of mcrs.Task)")
    try:
        inspect.signature(cls).bind(**settings)
    except TypeError as error:
        allowed = [p for p in inspect.signature(cls).parameters if p not in ("self", "args", "kwargs")]
        raise ConfigError(f"task: {cls.__name__}: {error}; its settings are {allowed}") from None
    try:
        return cls(**settings)
    except (TypeError, ValueError) as error:
        first = (str(error).strip().splitlines() or [type(error).__name__])[0]
        raise ConfigError(f"task ({target}): {first}") from None


def as_task(task: Task | EnvConfig) -> Task:
    """A task; an :class:`EnvConfig` stands for its :class:`MCRSTask`."""
    return MCRSTask(task) if isinstance(task, EnvConfig) else task


def with_agent_state(env: EnvBase, task: Task, num_envs: int, hidden_dim: int, device) -> TransformedEnv:
    """``env`` with what the recurrent acting policy reads: ``step_count`` when the env writes none, and the
    agents' carried state."""
    primer = recurrent_primer(num_envs, task.n_agents, hidden_dim, group=task.group, device=device)
    # a task's own TransformedEnv (StepCounter(max_steps)) is unwrapped: one chain of transforms
    if "step_count" in env.observation_spec:
        return TransformedEnv(env, primer, auto_unwrap=True)
    return TransformedEnv(env, Compose(StepCounter(), primer), auto_unwrap=True)


def _floating(dtype: torch.dtype) -> bool:
    return dtype.is_floating_point


def check_env(task: Task, env: EnvBase) -> None:
    """Raise :class:`ConfigError` where ``env``'s specs disagree with the task contract (the module
    docstring), naming the key and the value, instead of a shape error deep in torch later."""
    problems = []
    batch = tuple(env.batch_size)
    if len(batch) != 1:
        problems.append(f"its env's batch_size is {list(batch)}; the experiment needs [num_envs]")
        raise ConfigError(f"task {task.name!r} ({type(task).__name__}): " + "; ".join(problems))
    N, A = task.n_agents, task.n_actions
    contract = (  # key, spec, role, sizes per env, declared as, dtype test, dtype named
        (task.observation_key, env.observation_spec, "observation", (N, task.obs_dim),
         "n_agents, obs_dim", _floating, "float"),
        (task.action_mask_key, env.observation_spec, "observation", (N, A), "n_agents, n_actions",
         lambda dtype: dtype == torch.bool, "bool"),
        (task.state_key, env.observation_spec, "observation", tuple(task.state_shape), "state_shape",
         _floating, "float"),
        (task.action_key, env.full_action_spec, "action", (N,), "n_agents",
         lambda dtype: not dtype.is_floating_point and dtype != torch.bool, "integer"),
        ("reward", env.full_reward_spec, "reward", (1,), "the team reward (1,)",
         _floating, "float"),
        *(
            (key, env.full_done_spec, "done", (1,), "a flag (1,)", lambda dtype: dtype == torch.bool, "bool")
            for key in ("done", "terminated", "truncated")
        ),
    )  # fmt: skip
    for key, spec, role, sizes, declared, dtype_ok, dtype_name in contract:
        if key not in spec.keys(include_nested=True, leaves_only=True):
            problems.append(
                f"its env has no {role} key {key!r}, which the experiment reads"
                + (" (TorchRL's StepCounter(max_steps) writes it)" if key == "truncated" else "")
            )
            continue
        leaf = spec[key]
        shape = tuple(leaf.shape[len(batch) :])
        if shape != sizes:
            problems.append(f"{declared} = {sizes}, but its env's {key!r} is {shape} per env")
        elif not dtype_ok(leaf.dtype):
            problems.append(f"its env's {key!r} has dtype {leaf.dtype}; the experiment needs {dtype_name}")
        elif key == task.action_key:
            n = getattr(getattr(leaf, "space", None), "n", None)
            if n != A:
                problems.append(
                    f"n_actions = {A}, but its env's {key!r} is not a Categorical spec of {A} actions "
                    f"(space {getattr(leaf, 'space', None)})"
                )
    if problems:
        raise ConfigError(f"task {task.name!r} ({type(task).__name__}): " + "; ".join(problems))


def check_supported(config: Config, task: Task) -> None:
    """Raise :class:`ConfigError` naming every setting of ``config`` that ``task`` cannot run."""
    problems = unsupported(config, task)
    if problems:
        raise ConfigError(f"invalid config for task {task.name!r}:\n  - " + "\n  - ".join(problems))


def unsupported(config: Config, task: Task) -> list[str]:
    """The settings of ``config`` that ``task`` cannot run, one line each."""
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
        try:
            pickle.dumps(task)
        except Exception as error:  # what pickle raises depends on the object
            problems.append(
                f"train.collector=multiprocess: the workers build their environments from the task, and "
                f"task {task.name!r} cannot be pickled ({type(error).__name__}: {error}); "
                "use train.collector=single"
            )
    return problems
