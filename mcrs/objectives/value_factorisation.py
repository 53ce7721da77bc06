"""The value-factorisation TD loss over whole episodes, as a TorchRL :class:`LossModule`.

TorchRL's ``QMixerLoss`` works on single transitions with a feed-forward value network and no double-Q
target. Pymarl-style learners need recurrent agents unrolled over whole episodes, masked greedy choices,
double-Q targets and optionally TD(lambda). This loss adds those and reuses TorchRL's mixers, its target
parameters (so ``HardUpdate``/``SoftUpdate`` work) and the estimators of
:mod:`torchrl.objectives.value.functional`.

The input is an episode batch ``[B, T + 1]`` (:func:`mcrs.experiment.training.replay.episodes_from_rollout`
builds one from any collector batch). Keys, renamable with :meth:`set_keys`::

    observation   [B, T+1, N, obs]   o_0 .. o_T
    action_mask   [B, T+1, N, A]     bool; optional, all allowed when absent
    state         [B, T+1, *S]       s_0 .. s_T; QMIX and QPLEX only (state=observation works too)
    action        [B, T+1, N]        a_0 .. a_{T-1}, last row padding
    reward        [B, T+1, 1]        r_t of t -> t+1, last row padding; per agent [B, T+1, N, 1] is
                                     reduced by reward_reduction ("mean" as BenchMARL, or "sum")
    done          [B, T+1, 1]        the transition ends the episode
    terminated    [B, T+1, 1]        the transition ends in a terminal state (no bootstrap)
    filled        [B, T+1]           the transition is real; optional
    action_value  [B, T+1, N, A]     written by a TorchRL agent network, not read from the batch
    agent_inputs  [B, T+1, N, in]    optional recurrent-agent inputs built by the caller

The agent network is either :class:`~mcrs.models.agent.RecurrentAgent`, unrolled from a zero hidden state
so every item must start at a reset, or any TorchRL module writing per-agent values at ``action_value``.
The latter runs on every step at once, on a copy holding only its in_keys so the taken actions are never
overwritten, and items may start mid-episode. A missing key raises a ``KeyError`` naming where it usually
comes from.

Algorithms' callbacks add keys to the sampled batch in ``on_train_batch``: the memory's look-ups
(``memory_return``, ``memory_hit``, ``memory_ratio``; :class:`mcrs.memory.EpisodicLookup`) and EMC's
``intrinsic_reward``, added to the TD target only. ``memory_weight`` (lambda, eq. 32) adds ``lambda *
sum_hits (r_t + gamma H - Q_tot)^2 / n_valid``, so the term grows with the hit rate as EMC's does; an
``incentive`` (:mod:`mcrs.objectives.incentive`) adds its ``r_p`` to the TD target."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch.nn import functional as F
from torchrl.modules.models.multiagent import Mixer
from torchrl.objectives import LossModule
from torchrl.objectives.value.functional import td0_return_estimate, td_lambda_return_estimate

from mcrs.models.agent import RecurrentAgent
from mcrs.models.mixers import DMAQMixer, QPLEXMixer
from mcrs.objectives.incentive import INCENTIVES, Incentive, make_incentive

NEG_INF = -1e10  # "minus infinity" that stays finite under arithmetic (masked actions)


#: Where each key of the episode layout usually comes from (for the missing-key errors).
KEY_ORIGINS = {
    "observation": "the env's per-agent observation, kept by episodes_from_rollout(step_keys=...)",
    "action": "the policy's action, kept by episodes_from_rollout(action_key=...)",
    "state": "the env's global state, kept by episodes_from_rollout(step_keys=...); a task without one "
    "can use the stacked observations: loss.set_keys(state=('agents', 'observation'))",
    "reward": "written by episodes_from_rollout from ('next', reward_key)",
    "done": "written by episodes_from_rollout",
    "terminated": "written by episodes_from_rollout",
    "action_value": "written by the TorchRL agent network (QValueActor's action_value_key)",
    **dict.fromkeys(
        ("memory_return", "memory_hit", "memory_ratio"),
        "written by the episodic memory's callback, EpisodicMemoryCallback.on_train_batch (EpisodicLookup)",
    ),
}
REWARD_REDUCTIONS = ("mean", "sum")


def mask_unavailable(q: torch.Tensor, action_mask: torch.Tensor) -> torch.Tensor:
    """Return ``q`` with unavailable actions set so low that no argmax chooses them."""
    return q.masked_fill(~action_mask, NEG_INF)


class ValueFactorisationLoss(LossModule):
    """Double-Q TD loss of a mixed team value ``Q_tot = mixer(Q_1(a_1), ..., Q_N(a_N), s)``.

    Args:
        agent_network: the shared :class:`RecurrentAgent`, or a TorchRL ``TensorDictModule`` writing
            per-agent action values ``[*B, N, A]`` at ``action_value``, e.g. ``QValueActor`` over
            ``MultiAgentMLP``.
        mixer: ``VDNMixer``, :class:`~mcrs.models.mixers.QMixer`, :class:`~mcrs.models.mixers.DMAQMixer` or
            :class:`~mcrs.models.mixers.QPLEXMixer`.
        td_lambda: 0 for one-step targets (pymarl), in (0, 1] for TD(lambda) (pymarl2 uses 0.6).
        double_q: pick the bootstrap action with the online network rather than the target network.
        memory_weight: lambda of the one-step memory target (eq. 32); 0 switches it off.
        incentive: an :class:`~mcrs.objectives.incentive.Incentive` or its ``algo.incentive`` name.
        reward_reduction: ``"mean"`` or ``"sum"`` of per-agent rewards ``[..., N, 1]``.
        reward_scale: factor on the team reward and the memory's returns in every target, so ``Q_tot``
            learns that multiple of the env's return (docs/TRAINING.md). EMC's intrinsic reward is not
            scaled. Logged values are divided back into env units; the losses are in the learner's.
    """

    INCENTIVES = INCENTIVES

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read by the loss; change them with :meth:`set_keys`."""

        observation: NestedKey = ("agents", "observation")
        action: NestedKey = ("agents", "action")
        action_mask: NestedKey = ("agents", "action_mask")
        state: NestedKey = "state"
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"
        filled: NestedKey = "filled"
        memory_return: NestedKey = "memory_return"
        memory_hit: NestedKey = "memory_hit"
        memory_ratio: NestedKey = "memory_ratio"
        intrinsic_reward: NestedKey = "intrinsic_reward"
        action_value: NestedKey = ("agents", "action_value")
        agent_inputs: NestedKey = "agent_inputs"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    #: What every forward returns; the other terms' statistics come only with those terms (:attr:`out_keys`).
    BASE_OUT_KEYS = ("loss", "loss_td", "q_taken_mean", "target_mean", "td_error_abs")

    agent_network: RecurrentAgent | TensorDictModuleBase
    agent_network_params: TensorDictBase
    target_agent_network_params: TensorDictBase
    mixer: Mixer
    mixer_params: TensorDictBase
    target_mixer_params: TensorDictBase

    def __init__(
        self,
        agent_network: RecurrentAgent | TensorDictModuleBase,
        mixer: Mixer,
        *,
        gamma: float = 0.99,
        td_lambda: float = 0.0,
        double_q: bool = True,
        memory_weight: float = 0.0,
        incentive: Incentive | str = "none",
        reward_reduction: str = "mean",
        reward_scale: float = 1.0,
    ) -> None:
        super().__init__()
        if not isinstance(agent_network, RecurrentAgent | TensorDictModuleBase):
            raise TypeError(
                "agent_network must be a RecurrentAgent or a TorchRL TensorDictModule writing per-agent "
                f"action values (e.g. QValueActor over MultiAgentMLP), got {type(agent_network).__name__}"
            )
        if not isinstance(mixer, Mixer):
            raise TypeError(
                "mixer must be a TorchRL Mixer (VDNMixer, QMixer, DMAQMixer, QPLEXMixer), not a "
                f"{type(mixer).__name__}; this loss wraps it itself"
            )
        if reward_reduction not in REWARD_REDUCTIONS:
            raise ValueError(
                f"reward_reduction must be one of {', '.join(REWARD_REDUCTIONS)}, got {reward_reduction!r}"
            )
        self.reward_reduction = reward_reduction
        if not (reward_scale > 0 and math.isfinite(reward_scale)):
            raise ValueError(f"reward_scale must be a finite number > 0, got {reward_scale}")
        self.reward_scale = float(reward_scale)
        self.recurrent = isinstance(agent_network, RecurrentAgent)
        if memory_weight < 0:
            raise ValueError(f"memory_weight must be >= 0, got {memory_weight}")
        self.memory_weight, self.incentive = float(memory_weight), make_incentive(incentive)
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {gamma}")
        if not 0.0 <= td_lambda <= 1.0:
            raise ValueError(f"td_lambda must be in [0, 1], got {td_lambda}")
        self.gamma, self.td_lambda, self.double_q = float(gamma), float(td_lambda), bool(double_q)
        self.convert_to_functional(agent_network, "agent_network", create_target_params=True)
        self.convert_to_functional(mixer, "mixer", create_target_params=True)

    @property
    def out_keys(self) -> tuple[str, ...]:
        """Return what :meth:`forward` returns: :data:`BASE_OUT_KEYS` and the statistics of the terms in use.
        ``intrinsic_mean`` depends on the batch, so it is not listed."""
        keys = [*self.BASE_OUT_KEYS]
        if self.uses_memory:
            keys.append("memory_hit_rate")
        if self.memory_weight > 0:
            keys += ["loss_memory", "memory_target_mean"]
        if self.incentive != "none":
            keys.append("incentive_mean")
        return tuple(keys)

    @property
    def uses_memory(self) -> bool:
        """Whether batches must carry the memory look-ups."""
        return self.memory_weight > 0 or self.incentive.reads_memory

    @property
    def in_keys(self) -> list[NestedKey]:
        keys = self.tensor_keys
        observations = [keys.observation] if self.recurrent else list(self.agent_network.in_keys)
        in_keys = [*observations, keys.action, keys.action_mask, keys.reward, keys.done, keys.terminated]
        if self.mixer.needs_state:
            in_keys.append(keys.state)
        if self.uses_memory:
            in_keys += [keys.memory_return, keys.memory_hit]
        return in_keys + [getattr(keys, name) for name in self.incentive.in_keys]

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        """Do nothing: the returns come from TorchRL's functional estimators."""

    # ------------------------------------------------------------------ pieces, public for tests and reuse
    def require(self, tensordict: TensorDictBase, name: str) -> torch.Tensor:
        """Return ``tensordict[tensor_keys.<name>]``, or raise a ``KeyError`` naming where it comes from."""
        key = getattr(self.tensor_keys, name)
        value = tensordict.get(key, None)
        if value is None:
            raise KeyError(
                f"ValueFactorisationLoss: the batch has no {name} key {key!r} ({KEY_ORIGINS.get(name, '')}); "
                f"another key can be set with loss.set_keys({name}=...)"
            )
        return value

    def agent_inputs(self, episodes: TensorDictBase) -> torch.Tensor | TensorDictBase:
        """Return the recurrent agent's inputs ``[B, T+1, N, in]``, or for a TorchRL agent a shallow copy of
        the batch with its in_keys."""
        if not self.recurrent:
            in_keys = self.agent_network.in_keys
            missing = [key for key in in_keys if episodes.get(key, None) is None]
            if missing:
                raise KeyError(
                    f"ValueFactorisationLoss: the agent network reads {in_keys}; the batch lacks {missing} "
                    "(keep them with episodes_from_rollout(step_keys=...))"
                )
            return episodes.select(*in_keys)
        built = episodes.get(self.tensor_keys.agent_inputs, None)  # already built by a caller (EMC)
        if built is not None:
            return built
        actions = self.require(episodes, "action")
        last_action = torch.cat([torch.full_like(actions[:, :1], -1), actions[:, :-1]], dim=1)
        return self.agent_network.build_inputs(self.require(episodes, "observation"), last_action)

    def _run_agent(self, inputs: torch.Tensor | TensorDictBase) -> torch.Tensor:
        if self.recurrent:
            return self.agent_network.unroll(inputs)
        out = self.agent_network(inputs.copy())  # a fresh shallow copy: the inputs serve both nets
        value = out.get(self.tensor_keys.action_value, None)
        if value is None:
            raise KeyError(
                f"ValueFactorisationLoss: the agent network wrote no action_value key "
                f"{self.tensor_keys.action_value!r} (its out_keys: {self.agent_network.out_keys}); set "
                "the key it writes with loss.set_keys(action_value=...)"
            )
        return value

    def agent_values(
        self,
        episodes: TensorDictBase,
        target: bool = False,
        inputs: torch.Tensor | TensorDictBase | None = None,
    ) -> torch.Tensor:
        """Return per-agent action values ``[B, T+1, N, A]`` of the online or target network."""
        inputs = self.agent_inputs(episodes) if inputs is None else inputs
        if not target:
            return self._run_agent(inputs)
        with (
            torch.no_grad(),
            self.target_agent_network_params.to_module(self.agent_network, preserve_module_state=False),
        ):
            return self._run_agent(inputs)

    def mix(
        self,
        chosen: torch.Tensor,
        state: torch.Tensor,
        action: torch.Tensor,
        max_value: torch.Tensor,
        target: bool = False,
    ) -> torch.Tensor:
        """Return ``Q_tot [..., 1]`` from chosen values ``[..., N]`` with the online or target mixer."""
        args: list[torch.Tensor] = [chosen.unsqueeze(-1)]
        if self.mixer.needs_state:
            args.append(state.contiguous())  # TorchRL's mixers view() the state
        mixer = self.mixer
        if isinstance(mixer, DMAQMixer):
            args += [F.one_hot(action, mixer.n_actions).to(chosen.dtype), max_value.unsqueeze(-1)]
            if isinstance(mixer, QPLEXMixer):  # we know the actions: its explicit (DMAQMixer) form
                mixer = partial(DMAQMixer.forward, mixer)
        if not target:
            return mixer(*args)
        with torch.no_grad(), self.target_mixer_params.to_module(self.mixer, preserve_module_state=False):
            return mixer(*args)

    def targets(self, reward: torch.Tensor, next_value: torch.Tensor, done, terminated) -> torch.Tensor:
        """Return one-step or TD(lambda) targets ``[B, T, 1]`` from TorchRL's return estimators."""
        if self.td_lambda == 0.0:
            return td0_return_estimate(self.gamma, next_value, reward, terminated, done=done)
        return td_lambda_return_estimate(
            self.gamma, self.td_lambda, next_value, reward, done, terminated, time_dim=-2
        )

    @torch.no_grad()
    def bootstrap_values(
        self,
        tensordict: TensorDictBase,
        inputs: torch.Tensor | TensorDictBase | None = None,
        greedy_q: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Return ``[B, T+1, 1]``: the target network's ``Q_tot`` at every state under the bootstrap action
        (the online greedy one with double Q)."""
        action_mask = tensordict.get(self.tensor_keys.action_mask, None)
        state = self.require(tensordict, "state") if self.mixer.needs_state else None
        inputs = self.agent_inputs(tensordict) if inputs is None else inputs
        target_q = self.agent_values(tensordict, target=True, inputs=inputs)
        if action_mask is not None:
            target_q = mask_unavailable(target_q, action_mask)
        if greedy_q is None and self.double_q:
            greedy_q = self.agent_values(tensordict, inputs=inputs)
            greedy_q = greedy_q if action_mask is None else mask_unavailable(greedy_q, action_mask)
        chooser = greedy_q if self.double_q else target_q
        next_actions = chooser.argmax(-1)  # [B, T+1, N]: the bootstrap action at every state
        next_chosen = target_q.gather(-1, next_actions.unsqueeze(-1)).squeeze(-1)
        # QPLEX's learner: the target mixer sees the double-Q actions and the target net's own maxima.
        return self.mix(next_chosen, state, next_actions, target_q.max(-1).values, target=True)

    # ------------------------------------------------------------------ the loss
    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        keys = self.tensor_keys
        action_mask = tensordict.get(keys.action_mask, None)  # optional: absent means all allowed
        state = self.require(tensordict, "state") if self.mixer.needs_state else None
        reward = self.require(tensordict, "reward")[:, :-1]
        if reward.dim() == 4:  # per-agent rewards [B, T, N, 1] -> the team reward [B, T, 1]
            reward = reward.mean(-2) if self.reward_reduction == "mean" else reward.sum(-2)
        scale = self.reward_scale
        reward = reward * scale  # the learner's units (1: the env's)
        terminated = self.require(tensordict, "terminated")[:, :-1].bool()
        done = self.require(tensordict, "done")[:, :-1].bool()
        filled = tensordict.get(keys.filled, None)
        filled = torch.ones_like(reward[..., 0], dtype=torch.bool) if filled is None else filled[:, :-1]
        done = done.clone()
        done[:, -1] = True  # the batch ends: bootstrap there, never run a lambda-return across it

        # Both mixers run over all T+1 states because slicing would make TorchRL's mixers copy the state.
        all_actions = self.require(tensordict, "action")  # [B, T+1, N], the last row is padding
        inputs = self.agent_inputs(tensordict)  # built once for the online and the target network
        q = self.agent_values(tensordict, inputs=inputs)  # [B, T+1, N, A]
        chosen = q.gather(-1, all_actions.unsqueeze(-1)).squeeze(-1)
        greedy_q = q.detach() if action_mask is None else mask_unavailable(q.detach(), action_mask)
        q_tot = self.mix(chosen, state, all_actions, greedy_q.max(-1).values)[:, :-1]  # [B, T, 1]

        weight = filled.unsqueeze(-1).to(q_tot.dtype)
        n_valid = weight.sum().clamp(min=1.0)
        stats: dict[str, torch.Tensor] = {}  # the memory and curiosity terms', only where they exist
        target_reward = reward
        intrinsic = tensordict.get(keys.intrinsic_reward, None)
        if intrinsic is not None:  # EMC's curiosity: in the TD target only
            target_reward = target_reward + intrinsic[:, :-1]
        memory_return = hit = None
        if self.uses_memory:
            memory_return = self.require(tensordict, "memory_return")[:, :-1] * scale
            hit = self.require(tensordict, "memory_hit")[:, :-1].unsqueeze(-1).to(q_tot.dtype) * weight
            stats["memory_hit_rate"] = hit.sum() / n_valid

        with torch.no_grad():
            next_q_tot = self.bootstrap_values(tensordict, inputs, greedy_q)
            incentive = self.incentive.reward(  # EMU's r_p; None without an incentive
                memory_return,
                hit,
                next_q_tot[:, 1:],
                self.gamma,
                lambda name: self.require(tensordict, name)[:, :-1],
            )
            if incentive is not None:
                target_reward = target_reward + incentive
                stats["incentive_mean"] = incentive.sum() / n_valid / scale
            y = self.targets(target_reward, next_q_tot[:, 1:], done, terminated)

        td_error = (q_tot - y) * weight
        loss_td = td_error.pow(2).sum() / n_valid
        loss = loss_td
        if self.memory_weight > 0:  # eq. 32: the one-step memory target r_t + gamma * H(phi(s_{t+1}))
            memory_target = reward + self.gamma * memory_return
            loss_memory = ((q_tot - memory_target) * hit).pow(2).sum() / n_valid
            loss = loss + self.memory_weight * loss_memory
            stats["loss_memory"] = loss_memory
            stats["memory_target_mean"] = (memory_target * hit).sum() / hit.sum().clamp(min=1.0) / scale
        if intrinsic is not None:
            stats["intrinsic_mean"] = (intrinsic[:, :-1] * weight).sum() / n_valid
        return TensorDict(
            {
                "loss": loss,
                "loss_td": loss_td.detach(),
                "q_taken_mean": (q_tot.detach() * weight).sum() / n_valid / scale,
                "target_mean": (y * weight).sum() / n_valid / scale,
                "td_error_abs": td_error.detach().abs().sum() / n_valid / scale,
                **{k: v.detach() for k, v in stats.items()},
            },
            batch_size=[],
        )
