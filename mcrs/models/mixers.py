"""Value mixers in TorchRL's :class:`~torchrl.modules.models.multiagent.Mixer` family.

- :class:`VDNMixer` is TorchRL's, used as is.
- :class:`QMixer` adds pymarl's two-layer hypernetworks (``hypernet_layers=2``, the paper's default) to
  TorchRL's ``QMixer``; with ``hypernet_layers=1`` it is TorchRL's mixer.
- :class:`DMAQMixer` is QPLEX's ``dmaq`` mixer. It also needs the one-hot joint action and each agent's
  greedy value, which :class:`~mcrs.objectives.ValueFactorisationLoss` passes.
- :class:`QPLEXMixer` is the same mixer for TorchRL's ``QMixerLoss``: it reads only the keys that
  ``QValueModule`` and ``QMixerLoss`` write and derives the taken action and greedy value from them.

Every mixer maps chosen values ``[*B, N, 1]`` and the state ``[*B, *state_shape]`` to ``[*B, 1]``. As a
:class:`~tensordict.nn.TensorDictModule` it reads and writes (:func:`mixer_in_keys`)::

    ("agents", "chosen_action_value")   [*B, N, 1]  every mixer
    "state"                             [*B, S]     QMixer, DMAQMixer
    ("agents", "action_one_hot")        [*B, N, A]  DMAQMixer
    ("agents", "max_action_value")      [*B, N, 1]  DMAQMixer
    ("agents", "action_value")          [*B, N, A]  QPLEXMixer (masked actions very low)
    "chosen_action_value"               [*B, 1]     output

A task without a global state (VMAS) can pass the stacked observations: ``state_key=("agents",
"observation")``, ``state_shape=(N, obs_dim)``."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import nn
from torchrl.modules.models.multiagent import Mixer, VDNMixer
from torchrl.modules.models.multiagent import QMixer as TorchRLQMixer

from mcrs.choices import MIXERS

#: What a mixer's inputs usually come from, for the errors of :func:`mixer_module` users and of the loss.
KEY_ORIGINS = {
    "chosen_action_value": "written by TorchRL's QValueModule/QValueActor (and by QMixerLoss for the taken "
    "actions)",
    "action_value": "written by TorchRL's QValueModule/QValueActor (action_value_key)",
    "action_one_hot": "no TorchRL module writes it: use QPLEXMixer, which reads action_value instead",
    "max_action_value": "no TorchRL module writes it: use QPLEXMixer, which reads action_value instead",
}


def _hypernet(in_dim: int, out_dim: int, hidden: int, layers: int, device) -> nn.Module:
    if layers == 1:
        return nn.Linear(in_dim, out_dim, device=device)
    if layers == 2:
        return nn.Sequential(
            nn.Linear(in_dim, hidden, device=device), nn.ReLU(), nn.Linear(hidden, out_dim, device=device)
        )
    if layers == 3:
        return nn.Sequential(
            nn.Linear(in_dim, hidden, device=device),
            nn.ReLU(),
            nn.Linear(hidden, hidden, device=device),
            nn.ReLU(),
            nn.Linear(hidden, out_dim, device=device),
        )
    raise ValueError(f"hypernet_layers must be 1, 2 or 3, got {layers}")


class QMixer(TorchRLQMixer):
    """QMIX with pymarl's hypernetworks: ``hyper_w_1`` and ``hyper_w_final`` get ``hypernet_layers`` layers.
    Monotonicity (``dQ_tot/dQ_i >= 0``) comes from TorchRL's ``mix``, which takes absolute weights."""

    def __init__(
        self,
        state_shape: tuple[int, ...] | torch.Size,
        mixing_embed_dim: int,
        n_agents: int,
        device=None,
        hypernet_embed: int = 64,
        hypernet_layers: int = 2,
    ) -> None:
        super().__init__(state_shape, mixing_embed_dim, n_agents, device)
        self.hypernet_layers = hypernet_layers
        if hypernet_layers != 1:
            self.hyper_w_1 = _hypernet(
                self.state_dim, mixing_embed_dim * n_agents, hypernet_embed, hypernet_layers, device
            )
            self.hyper_w_final = _hypernet(
                self.state_dim, mixing_embed_dim, hypernet_embed, hypernet_layers, device
            )


class DMAQMixer(Mixer):
    """QPLEX's ``dmaq`` mixer: ``Q_tot = V_tot + A_tot``.

    ``V_tot = sum_i Q_i`` after a weighted head, and ``A_tot = sum_i (Q_i - maxQ_i).detach() * (lambda_i(s,
    a) - 1)``. The joint argmax of ``Q_tot`` is the agents' own argmaxes (IGM), because ``lambda_i > 0``
    and the weighted head is increasing.

    Args:
        hypernet_embed: hidden width of the weighted head's hypernetworks.
        n_kernels: attention heads of the advantage weights.
        adv_hypernet_layers: depth of the advantage-weight extractors (1, 2 or 3). QPLEX uses 1 on SMAC
            (``qplex_sc2.yaml``) and 3, with 10 heads, on its matrix games (``qplex.yaml``).
        adv_hypernet_embed: hidden width of those extractors when deeper than 1.
    """

    def __init__(
        self,
        state_shape: tuple[int, ...] | torch.Size,
        n_agents: int,
        n_actions: int,
        device=None,
        hypernet_embed: int = 64,
        n_kernels: int = 4,
        adv_hypernet_layers: int = 1,
        adv_hypernet_embed: int = 64,
    ) -> None:
        super().__init__(n_agents=n_agents, needs_state=True, state_shape=tuple(state_shape), device=device)
        self.n_actions, self.n_kernels = n_actions, n_kernels
        self.state_dim = int(math.prod(state_shape))
        # Weighted head: Q_i <- w_i(s) Q_i + v_i(s), w_i > 0.
        self.hyper_w = _hypernet(self.state_dim, n_agents, hypernet_embed, 2, device)
        self.hyper_v = _hypernet(self.state_dim, n_agents, hypernet_embed, 2, device)
        # Advantage weights lambda_i(s, a), n_kernels heads.
        joint = self.state_dim + n_agents * n_actions
        L, H = adv_hypernet_layers, adv_hypernet_embed
        self.key_extractors = _hypernet(self.state_dim, n_kernels, H, L, device)
        self.agents_extractors = _hypernet(self.state_dim, n_kernels * n_agents, H, L, device)
        self.action_extractors = _hypernet(joint, n_kernels * n_agents, H, L, device)

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        if len(inputs) != 4:
            raise ValueError(
                "DMAQMixer takes 4 inputs: chosen_action_value [*B, N, 1], state [*B, *state_shape], "
                f"action_one_hot [*B, N, A], max_action_value [*B, N, 1]; got {len(inputs)}"
            )
        chosen, state, action_one_hot, max_value = inputs
        if state.shape[len(state.shape) - len(self.state_shape) :] != self.state_shape:
            raise ValueError(
                f"DMAQMixer expected a state ending in {self.state_shape}, got {tuple(state.shape)}"
            )
        batch = chosen.shape[:-2]
        if state.shape[: state.dim() - len(self.state_shape)] != batch:
            raise ValueError(
                f"DMAQMixer: the state's batch dims {tuple(state.shape[: state.dim() - len(self.state_shape)])} "
                f"differ from chosen_action_value's {tuple(batch)}"
            )
        for name, value, tail in (
            ("chosen_action_value", chosen, (self.n_agents, 1)),
            ("action_one_hot", action_one_hot, (self.n_agents, self.n_actions)),
            ("max_action_value", max_value, (self.n_agents, 1)),
        ):
            if tuple(value.shape[-2:]) != tail or value.shape[:-2] != batch:
                raise ValueError(
                    f"DMAQMixer expected {name} of shape {(*batch, *tail)} (batch dims as chosen_action_value), "
                    f"got {tuple(value.shape)}"
                )
        return self.mix(chosen, state, action_one_hot, max_value)

    def advantage_weights(self, state: torch.Tensor, action_one_hot: torch.Tensor) -> torch.Tensor:
        """Return ``lambda_i(s, a)`` ``[M, N]`` (> 0) for flat ``state [M, S]`` and ``action_one_hot [M, N *
        A]``."""
        M, K, N = state.shape[0], self.n_kernels, self.n_agents
        key = self.key_extractors(state).abs().unsqueeze(-1) + 1e-10  # [M, K, 1]
        agents = torch.sigmoid(self.agents_extractors(state)).view(M, K, N)
        action = torch.sigmoid(self.action_extractors(torch.cat([state, action_one_hot], dim=-1))).view(
            M, K, N
        )
        return (key * agents * action).sum(dim=1)

    def mix(
        self,
        chosen_action_value: torch.Tensor,
        state: torch.Tensor,
        action_one_hot: torch.Tensor | None = None,
        max_action_value: torch.Tensor | None = None,
    ) -> torch.Tensor:
        batch = chosen_action_value.shape[:-2]
        N = self.n_agents
        s = state.reshape(-1, self.state_dim)
        q = chosen_action_value.reshape(-1, N)
        q_max = max_action_value.reshape(-1, N)
        w = self.hyper_w(s).abs() + 1e-10
        v = self.hyper_v(s)
        q = w * q + v
        q_max = w * q_max + v
        v_tot = q.sum(dim=-1)
        lam = self.advantage_weights(s, action_one_hot.reshape(-1, N * self.n_actions))
        a_tot = ((q - q_max).detach() * (lam - 1.0)).sum(dim=-1)
        return (v_tot + a_tot).view(*batch, 1)


class QPLEXMixer(DMAQMixer):
    """QPLEX for TorchRL's ``QMixerLoss``: ``QMixer``'s constructor plus ``n_actions``, and three inputs.

    ``forward(chosen_action_value [*B, N, 1], state [*B, *state_shape], action_value [*B, N, A])``.
    ``QMixerLoss`` re-runs the value network on a copy of the batch, so ``(group, "action")`` there holds
    the greedy action; the taken action survives only in ``chosen_action_value``. It is found as the first
    entry of ``action_value`` equal to it, the test ``QValueModule`` uses. The greedy value is
    ``action_value.max(-1)``, already masked by ``QValueModule``.

    Args:
        mixing_embed_dim: hidden width of QPLEX's hypernetworks (its ``hypernet_embed``; QPLEX's own
            ``mixing_embed_dim`` is unused in the reference code).
        n_kernels: attention heads of the advantage weights (QPLEX: 4 on SMAC, 10 on matrix games).
        adv_hypernet_layers: depth of the advantage-weight extractors (1 on SMAC, 3 on matrix games).
    """

    def __init__(
        self,
        state_shape: tuple[int, ...] | torch.Size,
        mixing_embed_dim: int,
        n_agents: int,
        n_actions: int,
        device=None,
        *,
        n_kernels: int = 4,
        adv_hypernet_layers: int = 1,
    ) -> None:
        if isinstance(n_actions, bool) or not isinstance(n_actions, int) or n_actions < 1:
            raise ValueError(
                f"QPLEXMixer: n_actions must be the number of discrete actions (an int >= 1), got "
                f"{n_actions!r}; the signature is QMixer's plus n_actions: "
                "(state_shape, mixing_embed_dim, n_agents, n_actions, device)"
            )
        super().__init__(
            tuple(state_shape),
            n_agents,
            n_actions,
            device,
            hypernet_embed=mixing_embed_dim,
            n_kernels=n_kernels,
            adv_hypernet_layers=adv_hypernet_layers,
            adv_hypernet_embed=mixing_embed_dim,
        )

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        if len(inputs) != 3:
            raise ValueError(
                "QPLEXMixer takes 3 inputs: chosen_action_value [*B, N, 1], state [*B, *state_shape], "
                f"action_value [*B, N, A] (in_keys of its TensorDictModule); got {len(inputs)}"
            )
        chosen, state, action_value = inputs
        tail = (self.n_agents, self.n_actions)
        if tuple(action_value.shape[-2:]) != tail or action_value.shape[:-2] != chosen.shape[:-2]:
            raise ValueError(
                f"QPLEXMixer expected action_value of shape {(*chosen.shape[:-2], *tail)} (batch dims as "
                f"chosen_action_value; {KEY_ORIGINS['action_value']}), got {tuple(action_value.shape)}"
            )
        action_value = action_value.detach()  # QPLEX's advantage stream is detached anyway
        match = action_value == chosen.detach()
        if not bool(match.any(-1).all()):
            raise ValueError(
                "QPLEXMixer: some chosen_action_value entries are not in action_value, so the taken action "
                "cannot be read from them; feed the values QMixerLoss or QValueModule gather from the same "
                "action_value (for explicit actions use DMAQMixer with action_one_hot and max_action_value)"
            )
        taken = match.to(torch.int8).argmax(-1)  # the first exact match
        one_hot = F.one_hot(taken, self.n_actions).to(chosen.dtype)
        max_value = action_value.max(-1, keepdim=True).values
        return super().forward(chosen, state, one_hot, max_value)


def make_mixer(
    name: str,
    n_agents: int,
    state_shape: Sequence[int],
    n_actions: int,
    mixing_embed_dim: int = 32,
    hypernet_embed: int = 64,
    hypernet_layers: int = 2,
    n_kernels: int = 4,
    adv_hypernet_layers: int = 1,
    device=None,
) -> Mixer:
    """Build a mixer by name (``qmix``, ``vdn``, ``qplex``)."""
    if name == "vdn":
        return VDNMixer(n_agents=n_agents, device=device)
    if name == "qmix":
        return QMixer(tuple(state_shape), mixing_embed_dim, n_agents, device, hypernet_embed, hypernet_layers)
    if name == "qplex":
        return DMAQMixer(
            tuple(state_shape),
            n_agents,
            n_actions,
            device,
            hypernet_embed,
            n_kernels,
            adv_hypernet_layers,
            hypernet_embed,
        )
    raise ValueError(f"unknown mixer {name!r}; allowed: {', '.join(MIXERS)}")


def mixer_in_keys(mixer: Mixer, group: str = "agents", state_key: NestedKey = "state") -> list[NestedKey]:
    """Return the tensordict keys a mixer reads, in ``forward``'s order."""
    keys: list[NestedKey] = [(group, "chosen_action_value")]
    if mixer.needs_state:
        keys.append(state_key)
    if isinstance(mixer, QPLEXMixer):
        keys.append((group, "action_value"))
    elif isinstance(mixer, DMAQMixer):
        keys += [(group, "action_one_hot"), (group, "max_action_value")]
    return keys


class MixerModule(TensorDictModule):
    """A mixer as a ``TensorDictModule`` whose missing-key error says where each key usually comes from."""

    def forward(self, tensordict: TensorDictBase, *args, **kwargs) -> TensorDictBase:
        missing = [key for key in self.in_keys if tensordict.get(key, None) is None]
        if missing:
            hints = []
            for key in missing:
                name = key[-1] if isinstance(key, tuple) else key
                origin = KEY_ORIGINS.get(
                    name,
                    "the env's global state; a task without one can mix on the stacked observations "
                    "(state_key=(group, 'observation'), state_shape=(n_agents, obs_dim))",
                )
                hints.append(f"{key!r} ({origin})")
            raise KeyError(f"{type(self.module).__name__} reads {self.in_keys}; missing: {'; '.join(hints)}")
        return super().forward(tensordict, *args, **kwargs)


def mixer_module(mixer: Mixer, group: str = "agents", state_key: NestedKey = "state") -> MixerModule:
    """Wrap a mixer as a TensorDictModule writing the root ``"chosen_action_value"``. The result is what
    TorchRL's ``QMixerLoss`` takes as ``mixer_network``."""
    return MixerModule(
        mixer, in_keys=mixer_in_keys(mixer, group, state_key), out_keys=["chosen_action_value"]
    )
