"""A task's run rebuilt by the tools: its task from the run's config, its trained agent and a random baseline.

A run of any task keeps how to rebuild it in its config (``task``,
:meth:`mcrs.experiment.training.task.Task.spec`). From it ``mcrs-eval policy=<run>`` plays the trained
agent and, on the same episodes, :class:`UniformAllowed`, and ``mcrs-export`` writes the agent. MCRS runs
have no ``task`` node and use :mod:`mcrs.policies.trained`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from mcrs.experiment.config import ConfigError
from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.training.evaluation import make_eval_env, rollout_greedy
from mcrs.experiment.training.task import Task, make_task
from mcrs.models.acting import make_acting_policy
from mcrs.models.agent import RecurrentAgent
from mcrs.policies.trained import looks_like_checkpoint, refuse_replay_block, resolve_checkpoint

#: The random baseline's name in every table of a task's evaluation.
RANDOM = "random"


def task_node(path: str | Path) -> dict[str, Any] | None:
    """Return the ``task`` node of the run or checkpoint ``path``, or None for an MCRS run or a non-run; only
    the config is read."""
    if not looks_like_checkpoint(str(path)) or str(path).endswith(".pt2"):
        return None
    try:
        file = resolve_checkpoint(path)
        if not file.is_file():
            return None
        state = ckpt.load(file, mmap=True)
    except (ckpt.CheckpointError, OSError):
        return None
    config = state.get("config") if isinstance(state, dict) else None
    node = config.get("task") if isinstance(config, dict) else None
    return node if isinstance(node, dict) else None


@dataclass(frozen=True)
class TaskRun:
    """A task run's trained agent, with its task rebuilt."""

    task: Task
    agent: RecurrentAgent
    path: Path  # the checkpoint file read
    config: dict[str, Any]  # the run's whole config, as saved
    env_steps: int | None


def load_task_run(path: str | Path) -> TaskRun:
    """Return the agent of the task run or checkpoint ``path`` with its task rebuilt from the run's config.
    Raises a one-line :class:`~mcrs.experiment.run.checkpoint.CheckpointError` when the task cannot be
    rebuilt or the agent does not fit it."""
    file = resolve_checkpoint(path)
    state = ckpt.load(file)
    refuse_replay_block(state, file)
    try:
        config = state["config"]
        task = make_task(config["task"])
        model, weights = config["model"], state["learner"]["agent"]
    except ConfigError as error:
        raise ckpt.CheckpointError(f"checkpoint {file}: its task cannot be rebuilt: {error}") from None
    except (KeyError, TypeError) as error:
        raise ckpt.CheckpointError(f"checkpoint {file} lacks a usable config or agent ({error!r})") from None
    try:
        agent = RecurrentAgent(
            task.obs_dim,
            task.n_actions,
            task.n_agents,
            model["hidden_dim"],
            model["agent_id"],
            model["last_action"],
        )
        agent.load_state_dict(weights)
    except (KeyError, TypeError, ValueError, RuntimeError) as error:
        first = (str(error).strip().splitlines() or [type(error).__name__])[0]
        raise ckpt.CheckpointError(
            f"checkpoint {file}: its agent does not fit its task {task.name!r}: {first}"
        ) from None
    counters = state.get("counters")
    steps = counters.get("env_steps") if isinstance(counters, dict) else None
    return TaskRun(task, agent.eval(), file, config, steps if isinstance(steps, int) else None)


class UniformAllowed(TensorDictModuleBase):
    """The random baseline of any task: each agent's action uniform over its allowed actions, from a generator
    seeded with ``seed``."""

    def __init__(self, task: Task, seed: int = 0) -> None:
        super().__init__()
        self.mask_key, self.action_key = task.action_mask_key, task.action_key
        self.in_keys, self.out_keys = [self.mask_key], [self.action_key]
        self.seed = seed
        self.generator: torch.Generator | None = None

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        mask = tensordict.get(self.mask_key)  # [E, N, A]
        if self.generator is None or self.generator.device != mask.device:
            self.generator = torch.Generator(device=mask.device).manual_seed(self.seed)
        weights = mask.reshape(-1, mask.shape[-1]).float()
        action = torch.multinomial(weights, 1, generator=self.generator).view(mask.shape[:-1])
        tensordict.set(self.action_key, action)
        return tensordict


def task_metrics(
    task: Task, policy: TensorDictModuleBase, episodes: int, seed: int, hidden_dim: int, device: str = "cpu"
) -> dict[str, torch.Tensor]:
    """Return every metric of ``task`` over ``episodes`` episodes of ``policy`` as ``{name: [K]}`` float64 on
    CPU. The episodes are one batch reset from ``seed``, so the same seed gives every policy the same
    episodes."""
    env = make_eval_env(task, episodes, hidden_dim, device)
    try:
        metrics = task.episode_metrics(rollout_greedy(env, policy, seed, task.max_steps))
    finally:
        env.close()
    return {name: value.to(device="cpu", dtype=torch.float64) for name, value in metrics.items()}


def evaluate_task_run(
    run: TaskRun, episodes: int, seed: int, device: str = "cpu", label: str | None = None
) -> dict[str, dict[str, torch.Tensor]]:
    """Evaluate the greedy trained agent and the random baseline on the same episodes; return ``{policy:
    {metric: [K]}}``."""
    hidden = run.agent.hidden_dim
    agent = run.agent.to(device)
    greedy, _, _ = make_acting_policy(agent, run.task.n_actions, group=run.task.group)
    return {
        label or str(run.path): task_metrics(run.task, greedy, episodes, seed, hidden, device),
        RANDOM: task_metrics(run.task, UniformAllowed(run.task, seed), episodes, seed, hidden, device),
    }


def task_description(run: TaskRun, format_name: str, version: int) -> dict[str, Any]:
    """Return what an exported task agent's ``mcrs.json`` says: the task node, the sizes and the program's
    inputs and outputs."""
    model, task = run.config["model"], run.task
    return {
        "format": format_name,
        "version": version,
        "source": str(run.path),
        "env_steps": run.env_steps,
        "algo": run.config.get("algo", {}).get("name"),
        "seed": run.config.get("seed"),
        "task": {**run.config["task"], "name": task.name},
        "model": {key: model[key] for key in ("hidden_dim", "agent_id", "last_action")},
        "n_agents": task.n_agents,
        "obs_dim": task.obs_dim,
        "n_actions": task.n_actions,
        "hidden_dim": int(model["hidden_dim"]),
        "inputs": {
            "observation": f"[E, N, obs_dim] float32: each agent's {task.observation_key!r}",
            "action_mask": f"[E, N, n_actions] bool: the task's {task.action_mask_key!r}",
            "last_action": "[E, N] int64: each agent's previous action, -1 at an episode's first step",
            "hidden": "[E, N, hidden_dim] float32: the returned hidden state, zeros at an episode's first step",
        },
        "outputs": {
            "action": f"[E, N] int64: the best allowed action of each agent, the task's {task.action_key!r}",
            "hidden": "[E, N, hidden_dim] float32: pass it back at the next step",
        },
    }
