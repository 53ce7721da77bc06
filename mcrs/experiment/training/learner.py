"""The learner: the agent and mixer networks, their TD loss, optimiser and target networks.

One :meth:`Learner.update` per sampled batch of episodes. What an algorithm adds (the memory's look-ups, EMC's
intrinsic reward) arrives as batch keys written by the callbacks, so the learner is the same for every
algorithm; the mixer, the loss and EMU's incentive are handed to it by the
:mod:`~mcrs.experiment.training.algorithms`.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import Any

import torch
from torch import nn
from torchrl.objectives import HardUpdate

from mcrs.env.config import EnvConfig
from mcrs.experiment.schema import AlgoConfig, ModelConfig, TrainConfig
from mcrs.experiment.training.task import Task, as_task
from mcrs.models.agent import RecurrentAgent
from mcrs.models.mixers import make_mixer
from mcrs.objectives import ValueFactorisationLoss
from mcrs.objectives.gradient import gradient_step
from mcrs.objectives.incentive import Incentive, make_incentive


def build_agent(model: ModelConfig, env_config: EnvConfig | Task) -> RecurrentAgent:
    """The agent network shared by all agents of the task."""
    task = as_task(env_config)
    return RecurrentAgent(
        task.obs_dim,
        task.n_actions,
        task.n_agents,
        model.hidden_dim,
        model.agent_id,
        model.last_action,
    )


def build_mixer(algo: AlgoConfig, env_config: EnvConfig | Task) -> nn.Module:
    """The algorithm's mixer (QMIX, VDN or QPLEX) over the task's global state."""
    task = as_task(env_config)
    return make_mixer(
        str(algo.mixer),
        task.n_agents,
        tuple(task.state_shape),
        task.n_actions,
        mixing_embed_dim=algo.mixing_embed_dim,
        hypernet_embed=algo.hypernet_embed,
        hypernet_layers=algo.hypernet_layers,
        n_kernels=algo.qplex_kernels,
        adv_hypernet_layers=algo.qplex_adv_layers,
    )


def build_loss(
    algo: AlgoConfig, agent: nn.Module, mixer: nn.Module, incentive: Incentive | None = None
) -> ValueFactorisationLoss:
    """The TD loss of ``algo`` over the agent and the mixer, with ``algo.incentive``'s incentive when none is
    given."""
    if incentive is None:
        incentive = make_incentive(str(algo.incentive), algo.incentive_threshold)
    return ValueFactorisationLoss(
        agent,
        mixer,
        gamma=algo.gamma,
        td_lambda=algo.td_lambda,
        double_q=algo.double_q,
        memory_weight=algo.memory_weight,
        incentive=incentive,
        reward_scale=algo.reward_scale,
    )


def make_optimizer(params: list[nn.Parameter], train: TrainConfig) -> torch.optim.Optimizer:
    """``train.optimizer`` over ``params``."""
    if str(train.optimizer) == "adam":
        return torch.optim.Adam(params, lr=train.lr, eps=train.optim_eps)
    return torch.optim.RMSprop(params, lr=train.lr, alpha=train.rmsprop_alpha, eps=train.optim_eps)


class Learner:
    """Networks, loss, optimiser and target updates; its state is the loss module's plus the optimiser's.

    ``mixer`` builds the mixer from the task right after the agent, so the networks draw their initial weights
    in that order. ``loss`` builds a :class:`~mcrs.objectives.ValueFactorisationLoss` (or a subclass) from the
    agent and the mixer. Both default to ``algo``'s, and the run's
    :class:`~mcrs.experiment.training.algorithms.Algorithm` passes them."""

    def __init__(
        self,
        algo: AlgoConfig,
        model: ModelConfig,
        train: TrainConfig,
        env_config: EnvConfig | Task,
        device: torch.device,
        *,
        mixer: Callable[[Task], nn.Module] | None = None,
        incentive: Incentive | None = None,
        loss: Callable[[nn.Module, nn.Module], ValueFactorisationLoss] | None = None,
    ) -> None:
        task = as_task(env_config)
        self.agent = build_agent(model, task).to(device)
        self.mixer = (mixer or partial(build_mixer, algo))(task).to(device)
        make_loss = loss or (lambda agent, mixer_: build_loss(algo, agent, mixer_, incentive))
        self.loss = make_loss(self.agent, self.mixer)
        if not isinstance(self.loss, ValueFactorisationLoss):
            raise TypeError(
                f"the learner's loss must be a ValueFactorisationLoss (or a subclass), got {type(self.loss).__name__}"
            )
        self.loss.set_keys(**task.loss_keys())
        self.params = [*self.agent.parameters(), *self.mixer.parameters()]
        self.optimizer = make_optimizer(self.params, train)
        # interval 0: every step() copies; the experiment calls it every target_update_episodes episodes.
        self.target_updater = HardUpdate(self.loss, value_network_update_interval=0)
        self.grad_clip = train.grad_clip

    def update(self, batch, step: int) -> dict[str, torch.Tensor]:
        """One gradient step; raises :class:`TrainingDiverged` before touching the weights on NaN or inf."""
        out = self.loss(batch)
        term = "loss"
        if not torch.isfinite(out["loss"]):  # name the term that broke (the memory term is weighted inside)
            term = next((k for k in ("loss_td", "loss_memory") if not torch.isfinite(out[k])), term)
        grad_norm = gradient_step(out["loss"], self.optimizer, self.params, self.grad_clip, step, term)
        stats = {k: v.detach() for k, v in out.items() if k != "loss"}
        return {**stats, "grad_norm": grad_norm.detach()}

    def weights(self) -> dict[str, Any]:
        """The online agent and mixer: what a policy needs."""
        return {"agent": self.agent.state_dict(), "mixer": self.mixer.state_dict()}

    def state_dict(self) -> dict[str, Any]:
        """The loss module's state (online and target networks) and the optimiser's, with ``agent`` and
        ``mixer`` for readers that want only the policy."""
        return {**self.weights(), "loss": self.loss.state_dict(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if "loss" in state:
            self.loss.load_state_dict(state["loss"])
        else:  # history.OLD_FORMS["learner without 'loss'"]
            self.agent.load_state_dict(state["agent"])
            self.mixer.load_state_dict(state["mixer"])
            self.loss.target_agent_network_params.load_state_dict(state["target_agent"])
            self.loss.target_mixer_params.load_state_dict(state["target_mixer"])
        self.optimizer.load_state_dict(state["optimizer"])
