"""The recurrent agent network shared by all agents (pymarl's RNN agent).

``Linear(in, H) -> ReLU -> GRU(H) -> Linear(H, n_actions)`` over the agent's observation, optionally
followed by the one-hot last action and the one-hot agent id, which lets shared parameters specialise.
Agents are folded into the batch, so one ``nn.GRU`` call unrolls every agent of every episode."""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from mcrs.models.gru import gru_sequence


class RecurrentAgent(nn.Module):
    """Per-agent Q network with parameter sharing.

    Args:
        hidden_dim: width of the input layer and of the GRU.
        agent_id: append the one-hot agent id to the input.
        last_action: append the one-hot previous action, zeros at the first step.
    """

    def __init__(
        self,
        obs_dim: int,
        n_actions: int,
        n_agents: int,
        hidden_dim: int = 64,
        agent_id: bool = True,
        last_action: bool = True,
    ) -> None:
        super().__init__()
        self.obs_dim, self.n_actions, self.n_agents, self.hidden_dim = (
            obs_dim,
            n_actions,
            n_agents,
            hidden_dim,
        )
        self.agent_id, self.last_action = agent_id, last_action
        self.input_dim = obs_dim + (n_actions if last_action else 0) + (n_agents if agent_id else 0)
        self.fc1 = nn.Linear(self.input_dim, hidden_dim)
        self.rnn = nn.GRU(hidden_dim, hidden_dim, batch_first=True)
        self.fc2 = nn.Linear(hidden_dim, n_actions)
        #: Unroll with :func:`mcrs.models.gru.gru_sequence` on CPU, which is cheaper; EMC's curiosity sets it.
        self.fused_cpu_gru = False

    def build_inputs(self, observation: torch.Tensor, last_action: torch.Tensor | None) -> torch.Tensor:
        """Concatenate ``observation [..., N, obs]`` with the optional one-hot inputs; ``last_action`` -1
        means none."""
        parts = [observation]
        if self.last_action:
            if last_action is None:
                raise ValueError("RecurrentAgent(last_action=True) needs the previous actions")
            one_hot = F.one_hot(last_action.clamp(min=0), self.n_actions).to(observation.dtype)
            parts.append(one_hot * (last_action >= 0).unsqueeze(-1).to(observation.dtype))
        if self.agent_id:
            eye = torch.eye(self.n_agents, device=observation.device, dtype=observation.dtype)
            parts.append(eye.expand(*observation.shape[:-1], self.n_agents))
        return torch.cat(parts, dim=-1) if len(parts) > 1 else observation

    def step(self, inputs: torch.Tensor, hidden: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Run one time step: ``inputs [..., N, in]``, ``hidden [..., N, H]`` -> ``(q [..., N, A], hidden)``."""
        lead = inputs.shape[:-1]
        x = F.relu(self.fc1(inputs)).reshape(1, -1, self.hidden_dim)
        h = hidden.reshape(1, -1, self.hidden_dim)
        _, h = self.rnn(x.transpose(0, 1), h)  # sequence of length 1, batch of every agent
        h = h.reshape(*lead, self.hidden_dim)
        return self.fc2(h), h

    def unroll(self, inputs: torch.Tensor) -> torch.Tensor:
        """Unroll whole episodes from a zero hidden state: ``inputs [B, T, N, in]`` -> ``q [B, T, N, A]``."""
        B, T, N, _ = inputs.shape
        if self.fused_cpu_gru and inputs.device.type == "cpu":  # time-major: each step's rows are contiguous
            x = self.fc1(inputs).transpose(0, 1).reshape(T, B * N, self.hidden_dim).relu_()
            return self.fc2(gru_sequence(x, self.rnn)).view(T, B, N, self.n_actions).transpose(0, 1)
        x = F.relu(self.fc1(inputs))  # [B, T, N, H]
        x = x.permute(0, 2, 1, 3).reshape(B * N, T, self.hidden_dim)  # agents folded into the batch
        out, _ = self.rnn(x)
        # fc2 on the contiguous GRU output: on the permuted view it runs as a much slower batched matmul.
        return self.fc2(out).reshape(B, N, T, self.n_actions).permute(0, 2, 1, 3)
