"""The value-factorisation TD loss over whole episodes, as a TorchRL :class:`LossModule`.

TorchRL's ``QMixerLoss`` works on single transitions with a feed-forward value network and no double-Q
target; pymarl-style learners need recurrent agents unrolled over whole episodes, masked greedy choices,
double-Q targets and optionally TD(lambda). This module does that and reuses TorchRL for the rest: any
TorchRL :class:`~torchrl.modules.models.multiagent.Mixer` (``VDNMixer``, our ``QMixer`` and ``DMAQMixer``),
the target parameters of :meth:`LossModule.convert_to_functional` (so ``HardUpdate``/``SoftUpdate`` work),
and the return estimators of :mod:`torchrl.objectives.value.functional`.

Input: an *episode batch* ``[B, T + 1]`` (see :func:`mcrs.experiment.replay.episodes_from_rollout`)::

    observation   [B, T+1, N, obs]   o_0 .. o_T (o_T is the final next observation)
    action_mask   [B, T+1, N, A]     bool, allowed actions at every step (the last row masks the targets)
    state         [B, T+1, *S]       s_0 .. s_T
    action        [B, T+1, N]        a_0 .. a_{T-1}, last row padding
    reward        [B, T+1, 1]        r_t of the transition t -> t+1, last row padding
    done          [B, T+1, 1]        the transition ends the episode (truncation or termination)
    terminated    [B, T+1, 1]        the transition ends in a terminal state (no bootstrap)
    filled        [B, T+1]           the transition is real (False on padding and on the last row)

The episodic-memory terms read, when switched on (row t describes the transition t -> t+1; see
:class:`mcrs.memory.EpisodicLookup`, the replay-buffer transform that attaches them)::

    memory_return [B, T+1, 1]        H(phi(s_{t+1})): the highest return stored near s_{t+1}
    memory_hit    [B, T+1]           a stored key lies within delta of phi(s_{t+1})
    memory_ratio  [B, T+1, 1]        N_xi / N_call of that entry (EMU's desirability), incentive="fixed"
    intrinsic_reward [B, T+1, 1]     a reward added to the TD target only (EMC's curiosity), optional

- ``memory_weight`` (lambda, eq. 32): ``loss += lambda * sum_hits (r_t + gamma H - Q_tot)^2 / n_valid``; a
  transition without a memory contributes nothing (the sum runs over hits, the mean over all valid
  transitions, so the term's weight grows with the hit rate, as EMC's does).
- ``incentive`` (EMU): ``r_p = gamma * ratio * max(H - Q_tot_target(s_{t+1}), 0)`` on hits, added to the TD
  target; ``"change"`` drops the ratio (EMU-change).

Keys are configurable with :meth:`set_keys` (``observation``, ``action``, ``action_mask``, ``state``,
``reward``, ``done``, ``terminated``, ``filled``, ``memory_return``, ``memory_hit``, ``memory_ratio``,
``intrinsic_reward``), so the loss plugs into other TorchRL multi-agent tasks.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch.nn import functional as F
from torchrl.modules.models.multiagent import Mixer
from torchrl.objectives import LossModule
from torchrl.objectives.value.functional import td0_return_estimate, td_lambda_return_estimate

from mcrs.models.agent import RecurrentAgent
from mcrs.models.mixers import DMAQMixer

NEG_INF = -1e10  # "minus infinity" that stays finite under arithmetic (masked actions)


def mask_unavailable(q: torch.Tensor, action_mask: torch.Tensor) -> torch.Tensor:
    """``q`` with unavailable actions set to a huge negative value: never chosen by any argmax."""
    return q.masked_fill(~action_mask, NEG_INF)


class ValueFactorisationLoss(LossModule):
    """Double-Q TD loss of a mixed team value ``Q_tot = mixer(Q_1(a_1), ..., Q_N(a_N), s)``.

    Args:
        agent_network: the shared recurrent agent (:class:`RecurrentAgent`).
        mixer: a TorchRL ``Mixer``: ``VDNMixer``, :class:`~mcrs.models.mixers.QMixer` or
            :class:`~mcrs.models.mixers.DMAQMixer`.
        gamma: discount factor.
        td_lambda: 0 for one-step targets (pymarl), in (0, 1] for TD(lambda) (pymarl2 uses 0.6).
        double_q: pick the bootstrap action with the online network (True) or the target network.
        memory_weight: lambda of the one-step memory target (eq. 32); 0 switches it off.
        incentive: EMU's episodic incentive: ``"none"``, ``"fixed"`` (scaled by the desirability ratio) or
            ``"change"`` (no ratio).
    """

    INCENTIVES = ("none", "fixed", "change")

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

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    out_keys: tuple[str, ...] = (
        "loss", "loss_td", "q_taken_mean", "target_mean", "td_error_abs",
        "loss_memory", "memory_hit_rate", "memory_target_mean", "incentive_mean", "intrinsic_mean",
    )  # fmt: skip

    agent_network: RecurrentAgent
    agent_network_params: TensorDictBase
    target_agent_network_params: TensorDictBase
    mixer: Mixer
    mixer_params: TensorDictBase
    target_mixer_params: TensorDictBase

    def __init__(
        self,
        agent_network: RecurrentAgent,
        mixer: Mixer,
        *,
        gamma: float = 0.99,
        td_lambda: float = 0.0,
        double_q: bool = True,
        memory_weight: float = 0.0,
        incentive: str = "none",
    ) -> None:
        super().__init__()
        if memory_weight < 0:
            raise ValueError(f"memory_weight must be >= 0, got {memory_weight}")
        if incentive not in self.INCENTIVES:
            raise ValueError(f"incentive must be one of {', '.join(self.INCENTIVES)}, got {incentive!r}")
        self.memory_weight, self.incentive = float(memory_weight), incentive
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {gamma}")
        if not 0.0 <= td_lambda <= 1.0:
            raise ValueError(f"td_lambda must be in [0, 1], got {td_lambda}")
        self.gamma, self.td_lambda, self.double_q = float(gamma), float(td_lambda), bool(double_q)
        self.convert_to_functional(agent_network, "agent_network", create_target_params=True)
        self.convert_to_functional(mixer, "mixer", create_target_params=True)

    @property
    def uses_memory(self) -> bool:
        """Whether batches must carry the memory look-ups (``memory_return``, ``memory_hit``...)."""
        return self.memory_weight > 0 or self.incentive != "none"

    @property
    def in_keys(self) -> list[NestedKey]:
        keys = self.tensor_keys
        in_keys = [keys.observation, keys.action, keys.action_mask, keys.state, keys.reward, keys.done]
        if self.uses_memory:
            in_keys += [keys.memory_return, keys.memory_hit]
        if self.incentive == "fixed":
            in_keys.append(keys.memory_ratio)
        return in_keys

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        """No TorchRL value estimator object: the returns come from its functional estimators."""

    # ------------------------------------------------------------------ pieces, public for tests and reuse
    def agent_inputs(self, episodes: TensorDictBase) -> torch.Tensor:
        """The agents' inputs ``[B, T+1, N, in]``: observations with the previous actions (and ids)."""
        keys = self.tensor_keys
        actions = episodes.get(keys.action)
        last_action = torch.cat([torch.full_like(actions[:, :1], -1), actions[:, :-1]], dim=1)
        return self.agent_network.build_inputs(episodes.get(keys.observation), last_action)

    def agent_values(
        self, episodes: TensorDictBase, target: bool = False, inputs: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Per-agent action values ``[B, T+1, N, A]`` from a zero hidden state (online or target net)."""
        inputs = self.agent_inputs(episodes) if inputs is None else inputs
        if not target:
            return self.agent_network.unroll(inputs)
        with (
            torch.no_grad(),
            self.target_agent_network_params.to_module(self.agent_network, preserve_module_state=False),
        ):
            return self.agent_network.unroll(inputs)

    def mix(
        self,
        chosen: torch.Tensor,
        state: torch.Tensor,
        action: torch.Tensor,
        max_value: torch.Tensor,
        target: bool = False,
    ) -> torch.Tensor:
        """``Q_tot [..., 1]`` from chosen values ``[..., N]`` (online or target mixer parameters)."""
        args: list[torch.Tensor] = [chosen.unsqueeze(-1)]
        if self.mixer.needs_state:
            args.append(state.contiguous())  # TorchRL's mixers view() the state
        if isinstance(self.mixer, DMAQMixer):
            args += [F.one_hot(action, self.mixer.n_actions).to(chosen.dtype), max_value.unsqueeze(-1)]
        if not target:
            return self.mixer(*args)
        with torch.no_grad(), self.target_mixer_params.to_module(self.mixer, preserve_module_state=False):
            return self.mixer(*args)

    def targets(self, reward: torch.Tensor, next_value: torch.Tensor, done, terminated) -> torch.Tensor:
        """One-step or TD(lambda) targets ``[B, T, 1]`` with TorchRL's return estimators."""
        if self.td_lambda == 0.0:
            return td0_return_estimate(self.gamma, next_value, reward, terminated, done=done)
        return td_lambda_return_estimate(
            self.gamma, self.td_lambda, next_value, reward, done, terminated, time_dim=-2
        )

    # ------------------------------------------------------------------ the loss
    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        keys = self.tensor_keys
        action_mask = tensordict.get(keys.action_mask)
        state = tensordict.get(keys.state)
        reward = tensordict.get(keys.reward)[:, :-1]
        terminated = tensordict.get(keys.terminated)[:, :-1].bool()
        done = tensordict.get(keys.done)[:, :-1].bool()
        filled = tensordict.get(keys.filled, None)
        filled = torch.ones_like(reward[..., 0], dtype=torch.bool) if filled is None else filled[:, :-1]
        done = done.clone()
        done[:, -1] = True  # the batch ends: bootstrap there, never run a lambda-return across it

        # Both mixers run over all T+1 states (the online one uses rows 0..T-1, the target one rows 1..T):
        # slicing [B, T+1, S] would make TorchRL's mixers copy the state, which costs more than one row.
        all_actions = tensordict.get(keys.action)  # [B, T+1, N], the last row is padding
        inputs = self.agent_inputs(tensordict)  # built once for the online and the target network
        q = self.agent_values(tensordict, inputs=inputs)  # [B, T+1, N, A]
        chosen = q.gather(-1, all_actions.unsqueeze(-1)).squeeze(-1)
        greedy_q = mask_unavailable(q.detach(), action_mask)
        q_tot = self.mix(chosen, state, all_actions, greedy_q.max(-1).values)[:, :-1]  # [B, T, 1]

        weight = filled.unsqueeze(-1).to(q_tot.dtype)
        n_valid = weight.sum().clamp(min=1.0)
        zero = q_tot.new_zeros(())
        stats = {"memory_hit_rate": zero, "memory_target_mean": zero, "incentive_mean": zero}
        target_reward = reward
        intrinsic = tensordict.get(keys.intrinsic_reward, None)
        if intrinsic is not None:  # EMC's curiosity: in the TD target only
            target_reward = target_reward + intrinsic[:, :-1]
        if self.uses_memory:
            memory_return = tensordict.get(keys.memory_return)[:, :-1]
            hit = tensordict.get(keys.memory_hit)[:, :-1].unsqueeze(-1).to(q_tot.dtype) * weight
            stats["memory_hit_rate"] = hit.sum() / n_valid

        with torch.no_grad():
            target_q = mask_unavailable(
                self.agent_values(tensordict, target=True, inputs=inputs), action_mask
            )
            chooser = greedy_q if self.double_q else target_q
            next_actions = chooser.argmax(-1)  # [B, T+1, N]: the bootstrap action at every state
            next_chosen = target_q.gather(-1, next_actions.unsqueeze(-1)).squeeze(-1)
            # QPLEX's learner: the target mixer sees the double-Q actions and the target net's own maxima.
            next_q_tot = self.mix(next_chosen, state, next_actions, target_q.max(-1).values, target=True)
            if self.incentive != "none":  # EMU: r_p = gamma * ratio * max(H(s') - Q_target(s'), 0)
                gap = (memory_return - next_q_tot[:, 1:]).clamp(min=0.0) * hit
                if self.incentive == "fixed":
                    gap = gap * tensordict.get(keys.memory_ratio)[:, :-1]
                incentive = self.gamma * gap
                target_reward = target_reward + incentive
                stats["incentive_mean"] = incentive.sum() / n_valid
            y = self.targets(target_reward, next_q_tot[:, 1:], done, terminated)

        td_error = (q_tot - y) * weight
        loss_td = td_error.pow(2).sum() / n_valid
        loss = loss_td
        loss_memory = zero
        if self.memory_weight > 0:  # eq. 32: the one-step memory target r_t + gamma * H(phi(s_{t+1}))
            memory_target = reward + self.gamma * memory_return
            loss_memory = ((q_tot - memory_target) * hit).pow(2).sum() / n_valid
            loss = loss + self.memory_weight * loss_memory
            stats["memory_target_mean"] = (memory_target * hit).sum() / hit.sum().clamp(min=1.0)
        return TensorDict(
            {
                "loss": loss,
                "loss_td": loss_td.detach(),
                "q_taken_mean": (q_tot.detach() * weight).sum() / n_valid,
                "target_mean": (y * weight).sum() / n_valid,
                "td_error_abs": td_error.detach().abs().sum() / n_valid,
                "loss_memory": loss_memory.detach(),
                "intrinsic_mean": zero if intrinsic is None else (intrinsic[:, :-1] * weight).sum() / n_valid,
                **{k: v.detach() for k, v in stats.items()},
            },
            batch_size=[],
        )
