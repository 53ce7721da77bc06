"""A task: what an :class:`~mcrs.experiment.training.trainer.Experiment` needs from an environment (BenchMARL's
``Task`` is the model).

The experiment builds every environment it uses (training, the collector's workers, evaluation) from the
task, reads the agents' and the mixer's sizes from it, points the loss and the acting policy at its keys and
logs the metrics it reports. :class:`MCRSTask` (the default, built from ``config.env``) is MCRS-LCR;
:class:`mcrs.tasks.matrix_game.MatrixGameTask` is a task we did not write. Bring your own by subclassing
:class:`Task` (docs/API.md, "Bring your own task")::

    Experiment(config, run_dir, task=MyTask()).run()

What a task's environment must be: a batched TorchRL ``EnvBase`` (``batch_size = [num_envs]``) with one
agent group. These are every key the experiment reads (``E`` envs, ``N`` agents, ``A`` actions), all checked
against the env's specs when the experiment builds the task (:func:`check_env`), before anything runs or is
written::

    (group, "observation")   [E, N, obs_dim]     float, at reset and every step
    (group, "action_mask")   [E, N, A]           bool, at reset and every step (all True: every action allowed)
    (group, "action")        [E, N]              int64 in 0..A-1 (action spec): what the experiment writes
    state_key                [E, *state_shape]   float, the mixer's global state, at reset and every step
    "reward"                 [E, 1]              float, the team's reward of the step
    "done"                   [E, 1]              bool: the episode ended at this step (terminated or truncated)
    "terminated"             [E, 1]              bool: it ended by the task (a goal, a failure): no bootstrap
    "truncated"              [E, 1]              bool: it ended by the time limit (the step ``max_steps``)

At the time limit an episode is ``done`` and ``truncated``; ``terminated`` is the task's own ending only
(an episode that reaches its goal on the last step is both). ``algo.time_limit`` says how a truncated step
enters the TD target: ``terminal`` (the default) treats it as terminal, ``bootstrap`` bootstraps from it.

Every episode ends by step ``max_steps``: the collector gathers ``[num_envs, max_steps]`` steps per batch,
each row from a reset, and each row's first episode is what the experiment keeps (an episode that ends
earlier is padded to ``max_steps`` and masked in the replay and the loss, as pymarl does; the steps the env
runs after it, its next episode, are dropped). ``step_count`` is added with TorchRL's ``StepCounter`` when
the env has none; the agents' recurrent state is added by the experiment.

A run records how to rebuild its task (:meth:`Task.spec`: an importable class and its settings, the
config's ``task`` node), so ``mcrs-eval policy=<run>``, ``mcrs-export`` and a resume rebuild it in any
process.
"""

from __future__ import annotations

import importlib
import inspect
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
    """An environment the experiment can train and evaluate on.

    Subclasses set ``name`` and the sizes, and implement :meth:`make_env`; the keys default to the
    group ``"agents"`` and the state ``"state"``; :meth:`episode_metrics` defaults to the episode reward.
    A task whose constructor takes arguments returns them from :meth:`settings`, so that its runs can be
    rebuilt (evaluated, exported, resumed) by the command-line tools. A task must be picklable for
    ``train.collector=multiprocess`` (its workers build their environments from it).
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
        """Per-episode metrics ``{name: [E]}`` of the rows ``[E, max_steps]`` of a rollout, each from a
        reset; the experiment logs their means (``train/<name>``, ``eval/<name>``). Must hold
        ``episode_reward``. Default: the reward summed over each row's first episode (to its first done)."""
        return {"episode_reward": first_episode_sum(rollout, ("next", "reward"))}

    def settings(self) -> dict[str, Any]:
        """The keyword arguments that rebuild this task (``type(self)(**settings)``), as plain values (str,
        numbers, bools, lists and dicts of them): the run's ``config.yaml`` keeps them. Default: none."""
        return {}

    def spec(self) -> dict[str, Any]:
        """How to rebuild the task: ``{"_target_": "<module>.<class>", **settings()}``, the config's
        ``task`` node (:func:`make_task` reads it)."""
        return {TARGET: f"{type(self).__module__}.{type(self).__qualname__}", **self.settings()}

    def fingerprint(self) -> dict[str, Any]:
        """What identifies the task in a checkpoint (a resume on another task is refused): plain values.
        A checkpoint written before tasks has none of these fields and resumes as MCRS. (The settings are
        in the fingerprint too, as the config's ``task`` node.)"""
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
        """What the replay keeps at every step (:func:`~mcrs.experiment.training.replay.episodes_from_rollout`)."""
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


#: The key of a task node that names its class (Hydra's spelling).
TARGET = "_target_"


def first_episode_sum(rollout: TensorDictBase, key: NestedKey) -> torch.Tensor:
    """``key`` (a reward, ``[E, T, ...]``) summed over each row's first episode: the steps up to and
    including the row's first ``("next", "done")``; ``[E]`` float32. A row of one episode: its whole sum."""
    E, T = rollout.batch_size
    value = rollout.get(key).float().reshape(E, T, -1).sum(-1)
    done = rollout.get(("next", "done")).reshape(E, T, -1).any(-1).long()
    return (value * ((done.cumsum(-1) - done) == 0)).sum(-1)


def make_task(node: Mapping[str, Any] | Task) -> Task:
    """The task a ``task`` node describes (``{"_target_": "pkg.module.Class", **settings}``, what
    :meth:`Task.spec` returns and a run's ``config.yaml`` keeps); a :class:`Task` is returned as it is.

    The target must be a :class:`Task` subclass importable in this process; its settings are the
    constructor's keyword arguments. Anything else is one :class:`ConfigError` line naming ``task.<key>``.
    """
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
    """A task; an :class:`EnvConfig` (what the builders took before tasks) is its :class:`MCRSTask`."""
    return MCRSTask(task) if isinstance(task, EnvConfig) else task


def with_agent_state(env: EnvBase, task: Task, num_envs: int, hidden_dim: int, device) -> TransformedEnv:
    """``env`` with what the recurrent acting policy reads: ``step_count`` (TorchRL's ``StepCounter``, when
    the env writes none) and the agents' carried state (:func:`~mcrs.models.acting.recurrent_primer`)."""
    primer = recurrent_primer(num_envs, task.n_agents, hidden_dim, group=task.group, device=device)
    # a task's own TransformedEnv (StepCounter(max_steps)) is unwrapped: one chain of transforms
    if "step_count" in env.observation_spec:
        return TransformedEnv(env, primer, auto_unwrap=True)
    return TransformedEnv(env, Compose(StepCounter(), primer), auto_unwrap=True)


def _floating(dtype: torch.dtype) -> bool:
    return dtype.is_floating_point


def check_env(task: Task, env: EnvBase) -> None:
    """Raise :class:`ConfigError` where ``env``'s specs disagree with the task contract (this module's
    docstring): a key the experiment reads that the env lacks, or a shape, dtype or size that differs from
    what ``task`` declares (``obs_dim``, ``n_agents``, ``n_actions``, ``state_shape``), naming the key, the
    attribute and the env's value. The networks are built from the declared sizes and the loop reads every
    key, so a mismatch would otherwise surface as a shape error deep in torch or a ``KeyError`` after the
    first evaluation."""
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
