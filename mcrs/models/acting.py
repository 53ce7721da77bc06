"""The acting policy: a recurrent agent step, a masked greedy choice, then masked epsilon-greedy exploration.

It is built from TorchRL's :class:`~torchrl.modules.QValueModule` and
:class:`~torchrl.modules.EGreedyModule`, with epsilon set in closed form, and a
:class:`~torchrl.envs.TensorDictPrimer` that carries the recurrent state and the last action between steps.
Both are reset at ``step_count == 0``, so the policy needs no reset hook.

Keys (``E`` envs, ``N`` agents, ``A`` actions, ``H`` hidden width)::

    reads   (group, "observation")          [E, N, obs]   the env
            (group, "action_mask")          [E, N, A]     the env (bool)
            (group, "rnn_hidden")           [E, N, H]     recurrent_primer
            (group, "last_action")          [E, N]        recurrent_primer
            "step_count"                    [E, 1]        TorchRL's StepCounter or MCRSEnv
    writes  (group, "action_value")         [E, N, A]
            (group, "action")               [E, N]        int64
            (group, "chosen_action_value")  [E, N, 1]
            ("next", group, "rnn_hidden"), ("next", group, "last_action")

A missing key raises a ``KeyError`` naming the transform that provides it."""

from __future__ import annotations

from typing import ClassVar

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import TensorDictPrimer
from torchrl.modules import EGreedyModule, QValueModule

from mcrs.models.agent import RecurrentAgent


class AgentStep(TensorDictModuleBase):
    """One recurrent step of the shared agent network for every env and agent of a batched tensordict."""

    def __init__(self, agent: RecurrentAgent, group: str = "agents") -> None:
        super().__init__()
        self.agent, self.group = agent, group
        g = group
        self.in_keys = [(g, "observation"), (g, "rnn_hidden"), (g, "last_action"), "step_count"]
        self.out_keys = [(g, "action_value"), ("next", g, "rnn_hidden")]

    #: Where each key read by the step usually comes from (for the missing-key error).
    ORIGINS: ClassVar[dict[str, str]] = {
        "observation": "the env's per-agent observation",
        "rnn_hidden": "add recurrent_primer(num_envs, n_agents, hidden_dim, group) to the env's transforms",
        "last_action": "add recurrent_primer(num_envs, n_agents, hidden_dim, group) to the env's transforms",
        "step_count": "add TorchRL's StepCounter() to the env's transforms",
    }

    @torch.no_grad()  # acting never needs gradients: training unrolls whole episodes instead
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        g = self.group
        missing = [key for key in self.in_keys if tensordict.get(key, None) is None]
        if missing:
            hints = "; ".join(
                f"{key!r}: {self.ORIGINS[key[-1] if isinstance(key, tuple) else key]}" for key in missing
            )
            raise KeyError(f"AgentStep reads {self.in_keys}; missing {hints}")
        obs = tensordict.get((g, "observation"))
        first = (tensordict.get("step_count") == 0).view(*obs.shape[:-2], 1)  # [E, 1]
        hidden = tensordict.get((g, "rnn_hidden")).masked_fill(first.unsqueeze(-1), 0.0)
        last_action = tensordict.get((g, "last_action")).masked_fill(first, -1)
        q, hidden = self.agent.step(self.agent.build_inputs(obs, last_action), hidden)
        tensordict.set((g, "action_value"), q)
        tensordict.set(("next", g, "rnn_hidden"), hidden)
        return tensordict


class RememberAction(TensorDictModuleBase):
    """Carry this step's actions to the next step as the agents' last-action input."""

    def __init__(self, group: str = "agents") -> None:
        super().__init__()
        self.group = group
        self.in_keys = [(group, "action")]
        self.out_keys = [("next", group, "last_action")]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict.set(("next", self.group, "last_action"), tensordict.get((self.group, "action")))
        return tensordict


class EpsilonGreedy(EGreedyModule):
    """TorchRL's masked epsilon-greedy with a closed-form linear schedule over env steps."""

    def set_env_steps(self, env_steps: int) -> float:
        """Set and return epsilon for ``env_steps`` collected so far."""
        start, end = float(self.eps_init), float(self.eps_end)
        fraction = min(1.0, env_steps / max(1, self.annealing_num_steps))
        eps = start + (end - start) * fraction
        self.eps.fill_(eps)
        return eps


def recurrent_primer(
    num_envs: int, n_agents: int, hidden_dim: int, group: str = "agents", device=None
) -> TensorDictPrimer:
    """Primer adding ``(group, "rnn_hidden")`` and ``(group, "last_action")`` to an env's specs."""
    E, N = num_envs, n_agents
    spec = Composite(
        {
            group: Composite(
                rnn_hidden=Unbounded(shape=(E, N, hidden_dim), dtype=torch.float32, device=device),
                last_action=Unbounded(shape=(E, N), dtype=torch.int64, device=device),
                shape=(E, N),
                device=device,
            )
        },
        shape=(E,),
        device=device,
    )
    return TensorDictPrimer(
        spec, default_value={(group, "rnn_hidden"): 0.0, (group, "last_action"): -1}, expand_specs=False
    )


def make_acting_policy(
    agent: RecurrentAgent,
    n_actions: int,
    *,
    eps_start: float = 1.0,
    eps_end: float = 0.05,
    eps_anneal_steps: int = 50_000,
    group: str = "agents",
) -> tuple[TensorDictSequential, TensorDictSequential, EpsilonGreedy]:
    """Return ``(greedy_policy, exploration_policy, epsilon_module)`` sharing the agent's parameters. Under
    ``ExplorationType.RANDOM``, the collector's default, the exploration policy draws a random allowed
    action per agent with probability epsilon."""
    device = next(agent.parameters()).device
    greedy = TensorDictSequential(
        AgentStep(agent, group),
        QValueModule(
            action_space="categorical",
            action_value_key=(group, "action_value"),
            action_mask_key=(group, "action_mask"),
            out_keys=[(group, "action"), (group, "action_value"), (group, "chosen_action_value")],
        ),
        RememberAction(group),
    )
    epsilon = EpsilonGreedy(
        spec=Categorical(n_actions, shape=(), dtype=torch.int64, device=device),
        eps_init=float(eps_start),
        eps_end=float(eps_end),
        annealing_num_steps=int(eps_anneal_steps),
        action_key=(group, "action"),
        action_mask_key=(group, "action_mask"),
        device=device,
    )
    exploring = TensorDictSequential(greedy[0], greedy[1], epsilon, greedy[2])
    return greedy, exploring, epsilon
