"""A trained agent from an ``mcrs-train`` checkpoint, behind the same interface as the heuristics.

The recurrent state restarts wherever ``step_count == 0``, so ``env.rollout``, ``mcrs-eval`` and
``mcrs-render`` run it like any heuristic. Actions are greedy among allowed moves."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import nn

from mcrs.env.config import EnvConfig, from_mapping, with_legacy_values
from mcrs.env.core import N_ACTIONS
from mcrs.experiment.run import checkpoint as ckpt
from mcrs.models.agent import RecurrentAgent
from mcrs.policies.base import ACTION_MASK, OBSERVATION, Policy

log = logging.getLogger(__name__)

#: Env fields that shape what a trained agent observes but not the task it plays (beyond the paper):
#: evaluations play a checkpoint with its own values of these (mcrs.policies.policy_env).
OBSERVATION_FIELDS = ("far_view", "no_fly_view", "relative_order")
#: Fields of the task a policy may be judged under whatever it was trained under (said, not refused): the
#: penalty and discovery rules, and whether zones are known (it changes r1 and the state; the surround
#: shows a zone as 0 under it, as no_fly_view=blocked does).
TASK_RULES = ("safety_rule", "discovery_rule", "no_fly_prior")
#: The file suffix of an exported agent (``mcrs-export``, mcrs.policies.export).
EXPORTED_SUFFIX = ".pt2"


def resolve_checkpoint(path: str | Path) -> Path:
    """Return a checkpoint file, or a run directory's latest ``model_<steps>.pt``, else its ``last.pt``."""
    path = Path(path).expanduser()
    try:
        if not path.is_dir():
            return path
        weights = sorted((path / "checkpoints").glob("model_*.pt"))
    except OSError as error:  # an unreadable directory
        raise ckpt.CheckpointError(f"checkpoint {path} cannot be read: {error.strerror or error}") from None
    return weights[-1] if weights else ckpt.checkpoint_path(path)


def trained_env(path: str | Path) -> EnvConfig | None:
    """Return the env config the checkpoint's agent was trained on, or None without a usable config. Fields
    the checkpoint predates take their defaults. Only the config is read; the tensors are mapped."""
    path = resolve_checkpoint(path)
    state = ckpt.load(path, mmap=True)
    refuse_replay_block(state, path)
    try:
        if state["config"].get("task") is not None:  # another task: its env is not the run's
            return None
        return from_mapping(with_legacy_values(state["config"]["env"])[0])
    except (KeyError, TypeError, ValueError, OverflowError):
        return None


def refuse_replay_block(state: Any, path: Path) -> None:
    """Refuse a ``checkpoints/replay_*.pt`` file, which holds episodes and no agent, naming what to pass
    instead."""
    if isinstance(state, dict) and "replay_block" in state:
        raise ckpt.CheckpointError(
            f"{path} is a block of its run's replay buffer (episodes), not a checkpoint: pass the run "
            "directory or a checkpoints/model_<steps>.pt file"
        )


def observation_settings(path: str | Path) -> dict[str, Any]:
    """Return the checkpoint's values of :data:`OBSERVATION_FIELDS`; none without a usable config."""
    trained = trained_env(path)
    return {} if trained is None else {name: getattr(trained, name) for name in OBSERVATION_FIELDS}


def looks_like_checkpoint(name: str) -> bool:
    """Whether a policy name is a path: a checkpoint, a run directory or an exported agent."""
    return name.endswith((".pt", EXPORTED_SUFFIX)) or "/" in name or Path(name).expanduser().is_dir()


def is_exported(name: str) -> bool:
    """Whether a policy name is an ``mcrs-export`` file."""
    return name.endswith(EXPORTED_SUFFIX)


class GreedyAgentStep(nn.Module):
    """One greedy step of the whole team, as one module.

    ``forward(observation [E, N, obs], action_mask [E, N, A], last_action [E, N], hidden [E, N, H]) ->
    (action [E, N], hidden)``, where ``last_action`` is -1 and ``hidden`` zeros at an episode's first step.
    The agent's index in N is its one-hot id. :class:`TrainedPolicy` acts through it and ``mcrs-export``
    writes it, so the deployed file computes what ``mcrs-eval`` scores."""

    def __init__(self, agent: RecurrentAgent) -> None:
        super().__init__()
        self.agent = agent

    def forward(
        self,
        observation: torch.Tensor,
        action_mask: torch.Tensor,
        last_action: torch.Tensor,
        hidden: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        q, hidden = self.agent.step(self.agent.build_inputs(observation, last_action), hidden)
        return q.masked_fill(~action_mask, float("-inf")).argmax(-1), hidden


@dataclass(frozen=True)
class TrainedAgent:
    """A checkpoint's agent with what it was trained on."""

    agent: RecurrentAgent
    env: EnvConfig  # the env config it was trained on
    path: Path  # the checkpoint file read
    config: dict[str, Any]  # the run's whole config, as saved
    env_steps: int | None  # the checkpoint's env steps (None: a file that does not say)
    legacy: bool  # the config predates a field and was read with its old default


def load_trained_agent(path: str | Path) -> TrainedAgent:
    """Return the agent of the checkpoint or run directory ``path``, refusing by name a file without a usable
    config or agent, or with non-finite weights."""
    path = resolve_checkpoint(path)
    state = ckpt.load(path)
    refuse_replay_block(state, path)
    task = state.get("config", {}).get("task") if isinstance(state.get("config"), dict) else None
    if isinstance(task, dict):  # its agent fits its own task, not the MCRS scenario of its config
        raise ckpt.CheckpointError(
            f"checkpoint {path} is a run of the task {task.get('name') or task.get('_target_')!r}, not of "
            "MCRS: evaluate it alone (mcrs-eval policy=<run>, which rebuilds its task)"
        )
    try:
        saved_env, legacy = with_legacy_values(state["config"]["env"])
        trained = from_mapping(saved_env)
        model = state["config"]["model"]
        weights = state["learner"]["agent"]
    except (KeyError, TypeError, ValueError, OverflowError) as error:  # 10**400 overflows float()
        reason = "; ".join(line.strip(" -") for line in str(error).splitlines() if line.strip())
        raise ckpt.CheckpointError(
            f"checkpoint {path} lacks a usable config or agent ({type(error).__name__}: {reason})"
        ) from None
    bad = [k for k, v in weights.items() if not isinstance(v, torch.Tensor) or not torch.isfinite(v).all()]
    if bad:  # NaN or inf weights would act (argmax of NaN) and be evaluated as a policy: refused
        raise ckpt.CheckpointError(
            f"checkpoint {path}: the agent's weights {', '.join(bad[:3])} hold NaN or inf (or are not "
            "tensors): not a trained policy"
        )
    try:
        agent = RecurrentAgent(
            trained.obs_dim,
            N_ACTIONS,
            trained.n_uavs,
            model["hidden_dim"],
            model["agent_id"],
            model["last_action"],
        )
        agent.load_state_dict(weights)
    except (KeyError, TypeError, ValueError, RuntimeError) as error:  # wrong shapes, missing fields
        first = (str(error).strip().splitlines() or [type(error).__name__])[0]
        raise ckpt.CheckpointError(f"checkpoint {path}: its agent cannot be built: {first}") from None
    counters = state.get("counters")
    env_steps = counters.get("env_steps") if isinstance(counters, dict) else None
    return TrainedAgent(
        agent.eval(),
        trained,
        path,
        state["config"],
        env_steps if isinstance(env_steps, int) else None,
        legacy,
    )


def check_playable(
    trained: EnvConfig, env_config: EnvConfig, source: str | Path, legacy: bool = False
) -> None:
    """Refuse an agent trained on ``trained`` playing ``env_config`` with another map, team or observation
    fields. The ValueError names the override. Only a differing task rule is warned about."""
    for rule in TASK_RULES:  # allowed (a policy judged under either rule): said
        if getattr(trained, rule) != getattr(env_config, rule):
            made = " (saved before the field existed)" if legacy else ""
            value = getattr(trained, rule)
            log.warning(
                "%s was trained under %s=%s%s; this environment uses %s=%s (pass env.%s=%s to evaluate it "
                "under its own rule)",
                source, rule, value, made, rule, getattr(env_config, rule), rule, value,
            )  # fmt: skip
    for field in OBSERVATION_FIELDS:
        if getattr(trained, field) != getattr(env_config, field):
            value = getattr(trained, field)
            raise ValueError(
                f"{source} was trained with env.{field}={value}; this environment has "
                f"env.{field}={getattr(env_config, field)}: pass env.{field}={value} (it shapes what the "
                "agent observes)"
            )
    differ = [f for f in ("width", "height", "n_uavs") if getattr(trained, f) != getattr(env_config, f)]
    if differ or trained.obs_dim != env_config.obs_dim:
        fields = " ".join(f"env.{f}={getattr(trained, f)}" for f in differ)
        advice = (  # the same preset with a field overridden: that field; another map: its preset
            f"pass {fields}" if trained.name == env_config.name and differ else f"pass env={trained.name}"
        )
        raise ValueError(
            f"{source} was trained on {trained.name} ({trained.width}x{trained.height}, "
            f"{trained.n_uavs} UAVs); this environment is {env_config.name} ({env_config.width}x"
            f"{env_config.height}, {env_config.n_uavs} UAVs): {advice}"
        )


class TrainedPolicy(Policy):
    """Greedy actions of a trained shared recurrent agent, from a checkpoint or an exported program."""

    def __init__(self, config: EnvConfig, step: nn.Module, hidden_dim: int, seed: int = 0) -> None:
        super().__init__(config, seed)
        self.step = step
        self.hidden_dim = hidden_dim
        self._hidden: torch.Tensor | None = None
        self._last_action: torch.Tensor | None = None

    @classmethod
    def from_checkpoint(cls, path: str | Path, env_config: EnvConfig, seed: int = 0) -> TrainedPolicy:
        """Load the agent of ``path``; ``env_config`` must have the map and team it was trained on."""
        trained = load_trained_agent(path)
        check_playable(trained.env, env_config, f"checkpoint {trained.path}", trained.legacy)
        agent = trained.agent.to(env_config.device)
        return cls(env_config, GreedyAgentStep(agent), agent.hidden_dim, seed)

    @property
    def agent(self) -> RecurrentAgent | None:
        """The checkpoint's agent network; None for an exported program."""
        return self.step.agent if isinstance(self.step, GreedyAgentStep) else None

    @torch.no_grad()
    def act(self, tensordict: TensorDictBase) -> torch.Tensor:
        obs, mask = tensordict.get(OBSERVATION), tensordict.get(ACTION_MASK)
        E, N = obs.shape[:2]
        if self._hidden is None or self._hidden.shape[0] != E:
            self._hidden = obs.new_zeros(E, N, self.hidden_dim)
            self._last_action = torch.full((E, N), -1, dtype=torch.int64, device=obs.device)
        first = (tensordict.get("step_count").view(E) == 0).view(E, 1)
        hidden = self._hidden.masked_fill(first.unsqueeze(-1), 0.0)
        last_action = self._last_action.masked_fill(first, -1)
        action, self._hidden = self.step(obs, mask, last_action, hidden)
        self._last_action = action
        return action
