"""A trained agent from an ``mcrs-train`` checkpoint, behind the same interface as the heuristics.

The recurrent state lives in the policy and restarts wherever ``step_count == 0``, so ``env.rollout``,
``mcrs-eval`` and ``mcrs-render`` run it like any heuristic. Actions are greedy among allowed moves.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase

from mcrs.env.config import EnvConfig, from_mapping, with_legacy_values
from mcrs.env.core import N_ACTIONS
from mcrs.experiment import checkpoint as ckpt
from mcrs.models.agent import RecurrentAgent
from mcrs.policies.base import ACTION_MASK, OBSERVATION, Policy

log = logging.getLogger(__name__)

#: Env fields that shape what a trained agent observes but not the task it plays (beyond the paper):
#: evaluations play a checkpoint with its own values of these (mcrs.policies.policy_env).
OBSERVATION_FIELDS = ("far_view",)


def resolve_checkpoint(path: str | Path) -> Path:
    """A checkpoint file, or a run directory: its latest ``model_<steps>.pt`` (weights only, small),
    else ``last.pt``."""
    path = Path(path).expanduser()
    try:
        if not path.is_dir():
            return path
        weights = sorted((path / "checkpoints").glob("model_*.pt"))
    except OSError as error:  # an unreadable directory
        raise ckpt.CheckpointError(f"checkpoint {path} cannot be read: {error.strerror or error}") from None
    return weights[-1] if weights else ckpt.checkpoint_path(path)


def observation_settings(path: str | Path) -> dict[str, Any]:
    """The checkpoint's values of :data:`OBSERVATION_FIELDS` (a config saved before one existed: its default,
    the paper's). A checkpoint without a usable config gives none: loading its policy then names the problem.
    The tensors are mapped, not read: only the config is needed here, and the policy loads the file next."""
    state = ckpt.load(resolve_checkpoint(path), mmap=True)
    try:
        trained = from_mapping(with_legacy_values(state["config"]["env"])[0])
    except (KeyError, TypeError, ValueError):
        return {}
    return {name: getattr(trained, name) for name in OBSERVATION_FIELDS}


def looks_like_checkpoint(name: str) -> bool:
    return name.endswith(".pt") or "/" in name or Path(name).expanduser().is_dir()


class TrainedPolicy(Policy):
    """Greedy actions of a trained shared recurrent agent."""

    def __init__(self, config: EnvConfig, agent: RecurrentAgent, seed: int = 0) -> None:
        super().__init__(config, seed)
        self.agent = agent.to(config.device).eval()
        self._hidden: torch.Tensor | None = None
        self._last_action: torch.Tensor | None = None

    @classmethod
    def from_checkpoint(cls, path: str | Path, env_config: EnvConfig, seed: int = 0) -> TrainedPolicy:
        """Load the agent of ``path``; ``env_config`` must have the map and team it was trained on."""
        path = resolve_checkpoint(path)
        state = ckpt.load(path)
        try:
            saved_env, legacy = with_legacy_values(state["config"]["env"])
            trained = from_mapping(saved_env)
            model = state["config"]["model"]
            weights = state["learner"]["agent"]
        except (KeyError, TypeError, ValueError) as error:
            reason = "; ".join(line.strip(" -") for line in str(error).splitlines() if line.strip())
            raise ckpt.CheckpointError(
                f"checkpoint {path} lacks a usable config or agent ({type(error).__name__}: {reason})"
            ) from None
        bad = [
            k for k, v in weights.items() if not isinstance(v, torch.Tensor) or not torch.isfinite(v).all()
        ]
        if bad:  # NaN or inf weights would act (argmax of NaN) and be evaluated as a policy: refused
            raise ckpt.CheckpointError(
                f"checkpoint {path}: the agent's weights {', '.join(bad[:3])} hold NaN or inf (or are not "
                "tensors): not a trained policy"
            )
        if trained.safety_rule != env_config.safety_rule:  # allowed (a policy judged under either rule): said
            made = " (saved before the field existed)" if legacy else ""
            log.warning(
                "checkpoint %s was trained under safety_rule=%s%s; this environment uses safety_rule=%s "
                "(pass env.safety_rule=%s to evaluate it under its own rule)",
                path, trained.safety_rule, made, env_config.safety_rule, trained.safety_rule,
            )  # fmt: skip
        for field in OBSERVATION_FIELDS:
            if getattr(trained, field) != getattr(env_config, field):
                value = getattr(trained, field)
                raise ValueError(
                    f"checkpoint {path} was trained with env.{field}={value}; this environment has "
                    f"env.{field}={getattr(env_config, field)}: pass env.{field}={value} (it shapes what the "
                    "agent observes)"
                )
        for field in ("width", "height", "n_uavs", "obs_dim"):
            if getattr(trained, field) != getattr(env_config, field):
                raise ValueError(
                    f"checkpoint {path} was trained on {trained.name} ({trained.width}x{trained.height}, "
                    f"{trained.n_uavs} UAVs); this environment is {env_config.name} ({env_config.width}x"
                    f"{env_config.height}, {env_config.n_uavs} UAVs): pass env={trained.name}"
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
        return cls(env_config, agent, seed)

    @torch.no_grad()
    def act(self, tensordict: TensorDictBase) -> torch.Tensor:
        obs, mask = tensordict.get(OBSERVATION), tensordict.get(ACTION_MASK)
        E, N = obs.shape[:2]
        if self._hidden is None or self._hidden.shape[0] != E:
            self._hidden = obs.new_zeros(E, N, self.agent.hidden_dim)
            self._last_action = torch.full((E, N), -1, dtype=torch.int64, device=obs.device)
        first = (tensordict.get("step_count").view(E) == 0).view(E, 1)
        hidden = self._hidden.masked_fill(first.unsqueeze(-1), 0.0)
        last_action = self._last_action.masked_fill(first, -1)
        q, self._hidden = self.agent.step(self.agent.build_inputs(obs, last_action), hidden)
        action = q.masked_fill(~mask, float("-inf")).argmax(-1)
        self._last_action = action
        return action
