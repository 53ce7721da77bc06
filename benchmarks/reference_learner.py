"""The plain-PyTorch reference learner: the fair anchor of ``mcrs-bench-learner``.

What it is: QMIX as a pymarl user writes it by hand - pymarl's RNN agent and QMIX mixer, the double-Q
one-step TD loss, RMSprop and gradient clipping - with no TorchRL and no tensordict; episodes sit in
preallocated plain tensors and are sampled with ``torch.randint``. It is not used for training.

Why: our learner (a TorchRL replay buffer, a ``LossModule``, functional target parameters) must not cost
much more per update than this. The comparison is only fair if both compute the same thing, so
:func:`check_agreement` starts it from our learner's weights and checks that the two losses agree to
``AGREE_RTOL`` on the same batch, before and after one update of each; the benchmark reports a
disagreement as a void comparison.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from torch import nn
from torch.nn import functional as F

from mcrs.env.config import EnvConfig
from mcrs.env.core import N_ACTIONS

AGREE_RTOL = 1e-5  # relative difference of the two losses that still counts as the same loss
NEG_INF = -1e10


def as_plain(episodes: TensorDictBase) -> dict[str, torch.Tensor]:
    """The tensors of an episode batch under the reference's flat names (no tensordict beyond here)."""
    return {
        "obs": episodes.get(("agents", "observation")),
        "mask": episodes.get(("agents", "action_mask")),
        "state": episodes.get("state"),
        "action": episodes.get(("agents", "action")),
        "reward": episodes.get("reward"),
        "terminated": episodes.get("terminated"),
        "filled": episodes.get("filled"),
    }


class ReferenceReplay:
    """Episodes in preallocated plain tensors ``[capacity, T + 1, ...]``; uniform sampling with replacement."""

    def __init__(self, episodes: dict[str, torch.Tensor], batch_size: int) -> None:
        self.data = {k: v.clone() for k, v in episodes.items()}
        self.size = next(iter(self.data.values())).shape[0]
        self.batch_size = batch_size

    def sample(self) -> dict[str, torch.Tensor]:
        idx = torch.randint(self.size, (self.batch_size,))
        return {k: v[idx] for k, v in self.data.items()}


class ReferenceAgent(nn.Module):
    """pymarl's RNN agent: ``Linear(in, H) -> ReLU -> GRU(H) -> Linear(H, A)``, agents folded into the batch."""

    def __init__(self, input_dim: int, hidden_dim: int, n_actions: int) -> None:
        super().__init__()
        self.hidden_dim = hidden_dim
        self.fc1 = nn.Linear(input_dim, hidden_dim)
        self.rnn = nn.GRU(hidden_dim, hidden_dim, batch_first=True)
        self.fc2 = nn.Linear(hidden_dim, n_actions)

    def forward(self, inputs: torch.Tensor) -> torch.Tensor:
        """``inputs [B, T, N, in]`` -> ``q [B, T, N, A]`` from a zero hidden state."""
        B, T, N, _ = inputs.shape
        x = F.relu(self.fc1(inputs)).transpose(1, 2).reshape(B * N, T, self.hidden_dim)
        out, _ = self.rnn(x)
        return self.fc2(out.reshape(B, N, T, self.hidden_dim).transpose(1, 2))


class ReferenceQMixer(nn.Module):
    """pymarl's QMIX mixer: 2-layer hypernetworks, absolute weights, ELU, a V(s) head."""

    def __init__(self, n_agents: int, state_dim: int, embed_dim: int, hypernet_embed: int) -> None:
        super().__init__()
        self.n_agents, self.state_dim, self.embed_dim = n_agents, state_dim, embed_dim
        self.hyper_w_1 = nn.Sequential(
            nn.Linear(state_dim, hypernet_embed), nn.ReLU(), nn.Linear(hypernet_embed, embed_dim * n_agents)
        )
        self.hyper_w_final = nn.Sequential(
            nn.Linear(state_dim, hypernet_embed), nn.ReLU(), nn.Linear(hypernet_embed, embed_dim)
        )
        self.hyper_b_1 = nn.Linear(state_dim, embed_dim)
        self.V = nn.Sequential(nn.Linear(state_dim, embed_dim), nn.ReLU(), nn.Linear(embed_dim, 1))

    def forward(self, qs: torch.Tensor, states: torch.Tensor) -> torch.Tensor:
        """``qs [B, T, N]``, ``states [B, T, S]`` -> ``q_tot [B, T, 1]``."""
        B, T = qs.shape[:2]
        s = states.reshape(-1, self.state_dim)
        q = qs.reshape(-1, 1, self.n_agents)
        w1 = self.hyper_w_1(s).abs().view(-1, self.n_agents, self.embed_dim)
        b1 = self.hyper_b_1(s).view(-1, 1, self.embed_dim)
        hidden = F.elu(torch.bmm(q, w1) + b1)
        w_final = self.hyper_w_final(s).abs().view(-1, self.embed_dim, 1)
        v = self.V(s).view(-1, 1, 1)
        return (torch.bmm(hidden, w_final) + v).view(B, T, 1)


class ReferenceLearner:
    """The update a pymarl user writes by hand: double-Q one-step TD loss of QMIX, RMSprop, grad clipping."""

    def __init__(self, cfg: DictConfig, env_config: EnvConfig) -> None:
        a, m, t = cfg.algo, cfg.model, cfg.train
        if (
            a.mixer != "qmix"
            or a.hypernet_layers != 2
            or a.td_lambda != 0.0
            or not (m.agent_id and m.last_action)
        ):
            raise ValueError(
                "the reference learner is QMIX with 2-layer hypernets, one-step targets, id and last action"
            )
        self.n_agents, self.n_actions = env_config.n_uavs, N_ACTIONS
        input_dim = env_config.obs_dim + N_ACTIONS + env_config.n_uavs
        self.agent = ReferenceAgent(input_dim, m.hidden_dim, N_ACTIONS)
        self.mixer = ReferenceQMixer(
            env_config.n_uavs, env_config.state_dim, a.mixing_embed_dim, a.hypernet_embed
        )
        self.target_agent = copy.deepcopy(self.agent)
        self.target_mixer = copy.deepcopy(self.mixer)
        self.gamma, self.double_q, self.grad_clip = float(a.gamma), bool(a.double_q), float(t.grad_clip)
        self.params = [*self.agent.parameters(), *self.mixer.parameters()]
        self.optimizer = torch.optim.RMSprop(self.params, lr=t.lr, alpha=t.rmsprop_alpha, eps=t.optim_eps)

    def load_weights(self, state: dict[str, Any]) -> None:
        """Online and target weights from :meth:`Learner.state_dict` (same parameter names)."""
        self.agent.load_state_dict(state["agent"])
        self.mixer.load_state_dict(state["mixer"])
        self.target_agent.load_state_dict(state["target_agent"])
        self.target_mixer.load_state_dict(state["target_mixer"])

    def build_inputs(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Observation, one-hot last action (zeros at t=0) and one-hot agent id: ``[B, T+1, N, in]``."""
        B, T1, N, _ = obs.shape
        last_action = torch.zeros(B, T1, N, self.n_actions, dtype=obs.dtype)
        last_action[:, 1:] = F.one_hot(action[:, :-1], self.n_actions).to(obs.dtype)
        ids = torch.eye(N, dtype=obs.dtype).expand(B, T1, N, N)
        return torch.cat([obs, last_action, ids], dim=-1)

    def loss(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        inputs = self.build_inputs(batch["obs"], batch["action"])
        actions, mask = batch["action"][:, :-1], batch["mask"]
        q = self.agent(inputs)  # [B, T+1, N, A]
        chosen = q[:, :-1].gather(-1, actions.unsqueeze(-1)).squeeze(-1)
        q_tot = self.mixer(chosen, batch["state"][:, :-1])
        with torch.no_grad():
            target_q = self.target_agent(inputs)[:, 1:].masked_fill(~mask[:, 1:], NEG_INF)
            chooser = q.detach()[:, 1:].masked_fill(~mask[:, 1:], NEG_INF) if self.double_q else target_q
            next_chosen = target_q.gather(-1, chooser.argmax(-1, keepdim=True)).squeeze(-1)
            next_q_tot = self.target_mixer(next_chosen, batch["state"][:, 1:])
            not_terminal = 1.0 - batch["terminated"][:, :-1].to(q_tot.dtype)
            y = batch["reward"][:, :-1] + self.gamma * not_terminal * next_q_tot
        weight = batch["filled"][:, :-1].unsqueeze(-1).to(q_tot.dtype)
        return ((q_tot - y) * weight).pow(2).sum() / weight.sum()

    def update(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        loss = self.loss(batch)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        nn.utils.clip_grad_norm_(self.params, self.grad_clip)
        self.optimizer.step()
        return loss.detach()


@dataclass
class Agreement:
    """The two learners' losses on the same batch, before and after one update of each."""

    ours: tuple[float, float]
    reference: tuple[float, float]

    @property
    def rel_diffs(self) -> tuple[float, ...]:
        return tuple(abs(o - r) / max(abs(r), 1e-12) for o, r in zip(self.ours, self.reference, strict=True))

    @property
    def agree(self) -> bool:
        return all(d <= AGREE_RTOL for d in self.rel_diffs)


def check_agreement(learner: Any, reference: ReferenceLearner, replay: Any) -> Agreement:
    """Loss of both on one batch; one update of both on that batch; loss of both on a second batch.

    The second comparison has target != online networks (so double-Q matters) and follows an optimiser
    step and gradient clipping of each, so it also checks that the updates are the same.
    """
    ours, ref = [], []
    first = replay.sample()
    with torch.no_grad():
        ours.append(learner.loss(first)["loss"].item())
        ref.append(reference.loss(as_plain(first)).item())
    learner.update(first, 0)
    reference.update(as_plain(first))
    second = replay.sample()
    with torch.no_grad():
        ours.append(learner.loss(second)["loss"].item())
        ref.append(reference.loss(as_plain(second)).item())
    return Agreement((ours[0], ours[1]), (ref[0], ref[1]))
