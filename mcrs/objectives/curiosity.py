"""EMC's curiosity (Zheng et al. 2021): an intrinsic reward from how badly a predictor predicts the Q values
of a separate VDN learner.

Each update the VDN learner takes one TD step and its target follows softly (tau 0.005). The predictor
learns to output 10x the soft target's Q values, and its error at ``t+1`` (L2 over actions, mean over
agents) times ``scale`` is the intrinsic reward of transition ``t``, added to the main TD target only. The
scale decays by ``decay_rate`` every ``decay_cycle`` env steps (EMC's SMAC setting: 0.001, 0.9, 100k).

Unlike EMC's code, which keeps a third copy, the predictor chases the VDN learner's own target network."""

from __future__ import annotations

import copy
from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.modules.models.multiagent import VDNMixer
from torchrl.objectives import SoftUpdate

from mcrs.models.agent import RecurrentAgent
from mcrs.objectives.gradient import gradient_step
from mcrs.objectives.value_factorisation import ValueFactorisationLoss

PREDICTION_SCALE = 10.0  # EMC multiplies the soft target's Q values by 10 before the prediction error


class EMCCuriosity(nn.Module):
    """The VDN learner, its soft target and the predictor; :meth:`update` returns the intrinsic reward.

    Args:
        agent: the network whose architecture the VDN learner and the predictor copy with fresh parameters.
        scale, decay_rate, decay_cycle: the intrinsic reward scale and its step decay.
        make_optimizer: builds an optimiser over a parameter list; pymarl's RMSprop (lr 5e-4, alpha 0.99,
            eps 1e-5) by default.
    """

    def __init__(
        self,
        agent: RecurrentAgent,
        *,
        gamma: float = 0.99,
        scale: float = 0.001,
        decay_rate: float = 0.9,
        decay_cycle: int = 100_000,
        tau: float = 0.005,
        grad_clip: float = 10.0,
        make_optimizer: Callable[[list[nn.Parameter]], torch.optim.Optimizer] | None = None,
    ) -> None:
        super().__init__()
        if scale < 0:
            raise ValueError(f"scale must be >= 0, got {scale}")
        if not 0.0 < decay_rate <= 1.0:
            raise ValueError(f"decay_rate must be in (0, 1], got {decay_rate}")
        if decay_cycle < 1:
            raise ValueError(f"decay_cycle must be >= 1 env step, got {decay_cycle}")
        if not 0.0 < tau <= 1.0:
            raise ValueError(f"tau must be in (0, 1], got {tau}")
        self.base_scale, self.decay_rate, self.decay_cycle = float(scale), float(decay_rate), int(decay_cycle)
        self.scale = self.base_scale
        self.grad_clip = float(grad_clip)
        device = next(agent.parameters()).device
        vdn_agent = _fresh_copy(agent)
        self.vdn_loss = ValueFactorisationLoss(
            vdn_agent, VDNMixer(n_agents=agent.n_agents, device=device), gamma=gamma
        )
        self.soft_update = SoftUpdate(self.vdn_loss, tau=tau)
        self.predictor = _fresh_copy(agent)
        for network in (vdn_agent, self.predictor):  # nn.GRU's values to float rounding, less CPU time
            network.fused_cpu_gru = True
        make = make_optimizer or _pymarl_rmsprop
        self.vdn_params = list(vdn_agent.parameters())
        self.predictor_params = list(self.predictor.parameters())
        self.vdn_optimizer = make(self.vdn_params)
        self.predictor_optimizer = make(self.predictor_params)

    def set_env_steps(self, env_steps: int) -> float:
        """Set the scale for ``env_steps`` in closed form, so a resumed run keeps the schedule."""
        self.scale = self.base_scale * self.decay_rate ** (int(env_steps) // self.decay_cycle)
        return self.scale

    def update(self, episodes: TensorDictBase, step: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Train on ``episodes`` ``[B, T+1]``; return the intrinsic reward ``[B, T+1, 1]`` (last row padding)
        and diagnostics."""
        # The agent inputs, built once for the four unrolls (a shallow copy: the caller's batch stays as it was).
        inputs = self.vdn_loss.agent_inputs(episodes)
        shared = episodes.copy().set(self.vdn_loss.tensor_keys.agent_inputs, inputs)
        vdn = self.vdn_loss(shared)
        gradient_step(vdn["loss"], self.vdn_optimizer, self.vdn_params, self.grad_clip, step, "curiosity_vdn")
        self.soft_update.step()

        target = self.vdn_loss.agent_values(shared, target=True, inputs=inputs) * PREDICTION_SCALE
        error = (self.predictor.unroll(inputs) - target).norm(dim=-1)  # [B, T+1, N]
        filled = episodes.get(self.vdn_loss.tensor_keys.filled)[:, :-1]  # transitions t whose s_{t+1} counts
        valid = filled.unsqueeze(-1).to(error.dtype)
        next_error = error[:, 1:]  # the prediction error at t+1, for transition t
        n = (valid.sum() * error.shape[-1]).clamp(min=1.0)
        prediction_loss = (next_error * valid).sum() / n
        gradient_step(
            prediction_loss, self.predictor_optimizer, self.predictor_params, self.grad_clip, step,
            "curiosity_prediction",
        )  # fmt: skip
        intrinsic = torch.zeros_like(error[..., :1])
        intrinsic[:, :-1] = self.scale * next_error.detach().mean(-1, keepdim=True) * valid
        stats = {
            "curiosity_loss_vdn": vdn["loss_td"],
            "curiosity_loss_prediction": prediction_loss.detach(),
            "curiosity_scale": torch.tensor(self.scale),
        }
        return intrinsic, stats

    def state_dict_all(self) -> dict:
        """Return the networks, soft target and optimisers for checkpoints."""
        return {
            "modules": self.state_dict(),
            "vdn_optimizer": self.vdn_optimizer.state_dict(),
            "predictor_optimizer": self.predictor_optimizer.state_dict(),
        }

    def load_state_dict_all(self, state: dict) -> None:
        self.load_state_dict(state["modules"])
        self.vdn_optimizer.load_state_dict(state["vdn_optimizer"])
        self.predictor_optimizer.load_state_dict(state["predictor_optimizer"])


def _fresh_copy(agent: nn.Module) -> nn.Module:
    """A module of the same architecture with newly initialised parameters."""
    clone = copy.deepcopy(agent)
    for module in clone.modules():
        if module is not clone and hasattr(module, "reset_parameters"):
            module.reset_parameters()
    return clone


def _pymarl_rmsprop(params: list[nn.Parameter]) -> torch.optim.Optimizer:
    return torch.optim.RMSprop(params, lr=5e-4, alpha=0.99, eps=1e-5)
