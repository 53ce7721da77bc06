"""The mixers: the properties each paper relies on, checked numerically on random inputs and weights.

QMIX must be monotonic in every agent value, VDN a plain sum, and QPLEX's dmaq mixer must satisfy IGM (the
joint argmax is the agents' own argmaxes) through its duplex dueling formula, which we re-derive here.
"""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torch.nn import functional as F
from torchrl.modules.models.multiagent import QMixer as TorchRLQMixer
from torchrl.modules.models.multiagent import VDNMixer

from mcrs.models.mixers import DMAQMixer, QMixer, make_mixer, mixer_in_keys, mixer_module

SEEDS = [0, 1, 2]


def _scramble(module: torch.nn.Module, seed: int, scale: float = 1.0) -> None:
    """Replace the (small) initial weights by larger random ones: the properties must hold for any weights."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * scale)


# ---------------------------------------------------------------------------------------------- QMIX, VDN
@pytest.mark.parametrize("hypernet_layers", [1, 2])
@pytest.mark.parametrize("seed", SEEDS)
def test_qmixer_is_monotonic_in_every_agent_value(hypernet_layers: int, seed: int) -> None:
    torch.manual_seed(seed)
    n_agents, state_dim = 4, 6
    mixer = QMixer((state_dim,), 8, n_agents, hypernet_embed=16, hypernet_layers=hypernet_layers)
    _scramble(mixer, seed)
    chosen = (torch.randn(5, 7, n_agents, 1) * 5).requires_grad_()
    state = torch.randn(5, 7, state_dim)
    q_tot = mixer(chosen, state)
    assert q_tot.shape == (5, 7, 1)
    (grad,) = torch.autograd.grad(q_tot.sum(), chosen)
    assert (grad >= 0).all(), "dQ_tot/dQ_i must be non-negative (QMIX's monotonicity)"
    # And in finite steps: raising one agent's value never lowers Q_tot.
    for agent in range(n_agents):
        bumped = chosen.detach().clone()
        bumped[..., agent, :] += torch.rand(5, 7, 1) * 3
        assert (mixer(bumped, state) >= q_tot.detach() - 1e-5).all()


def test_qmixer_with_one_hypernet_layer_is_torchrl_qmixer() -> None:
    ours = QMixer((6,), 8, 3, hypernet_layers=1)
    theirs = TorchRLQMixer((6,), 8, 3, device=None)
    assert {k: v.shape for k, v in ours.state_dict().items()} == {
        k: v.shape for k, v in theirs.state_dict().items()
    }
    assert sum(p.numel() for p in ours.parameters()) == sum(p.numel() for p in theirs.parameters())
    ours.load_state_dict(theirs.state_dict())
    chosen, state = torch.randn(10, 3, 1), torch.randn(10, 6)
    torch.testing.assert_close(ours(chosen, state), theirs(chosen, state))


def test_qmixer_two_hypernet_layers_are_pymarls() -> None:
    mixer = QMixer((6,), 8, 3, hypernet_embed=16, hypernet_layers=2)
    shapes = [p.shape for p in mixer.hyper_w_1.parameters()]
    assert shapes == [(16, 6), (16,), (8 * 3, 16), (8 * 3,)]  # state -> embed -> mixing weights
    assert [p.shape for p in mixer.hyper_w_final.parameters()] == [(16, 6), (16,), (8, 16), (8,)]
    with pytest.raises(ValueError, match="hypernet_layers"):
        QMixer((6,), 8, 3, hypernet_layers=0)


def test_vdn_is_the_sum() -> None:
    mixer = make_mixer("vdn", 3, (6,), 5)
    assert isinstance(mixer, VDNMixer)
    chosen = torch.randn(4, 2, 3, 1)
    torch.testing.assert_close(mixer(chosen), chosen.sum(dim=-2))


def test_make_mixer_rejects_unknown_names() -> None:
    with pytest.raises(ValueError, match="unknown mixer"):
        make_mixer("qtran", 3, (6,), 5)


# ---------------------------------------------------------------------------------------------- QPLEX
N_AGENTS, N_ACTIONS, STATE_DIM = 3, 4, 5


def _all_joint_actions(n_agents: int, n_actions: int) -> torch.Tensor:
    """``[A^N, N]``: every joint action, row-major (agent 0 slowest)."""
    index = torch.arange(n_actions**n_agents)
    return torch.stack(torch.unravel_index(index, (n_actions,) * n_agents), dim=-1)


def _qplex_table(mixer: DMAQMixer, q: torch.Tensor, state: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Q_tot of every joint action for per-agent values ``q [N, A]``, with each agent's max as ``maxQ_i``."""
    joint = _all_joint_actions(*q.shape)
    M = joint.shape[0]
    chosen = q.expand(M, *q.shape).gather(-1, joint.unsqueeze(-1))  # [M, N, 1]
    best = q.max(-1, keepdim=True).values.expand(M, q.shape[0], 1)
    one_hot = F.one_hot(joint, q.shape[1]).float()
    q_tot = mixer(chosen, state.expand(M, -1), one_hot, best)
    return q_tot.squeeze(-1), joint, chosen.squeeze(-1), best.squeeze(-1), one_hot


@pytest.mark.parametrize("seed", SEEDS)
def test_qplex_satisfies_igm_and_its_duplex_dueling_formula(seed: int) -> None:
    torch.manual_seed(seed)
    mixer = DMAQMixer((STATE_DIM,), N_AGENTS, N_ACTIONS, hypernet_embed=16, n_kernels=4)
    _scramble(mixer, seed, scale=0.7)
    q = torch.randn(N_AGENTS, N_ACTIONS) * 3
    state = torch.randn(1, STATE_DIM)
    with torch.no_grad():
        q_tot, joint, chosen, best, one_hot = _qplex_table(mixer, q, state)

        # IGM: the joint argmax is the agents' own argmaxes, and every other joint action is strictly worse.
        greedy = q.argmax(-1)
        top = q_tot.argmax()
        assert torch.equal(joint[top], greedy)
        others = ~(joint == greedy).all(-1)
        assert (q_tot[others] < q_tot[top]).all()

        # The formula, from the code: with W_i = w_i(s) Q_i + v_i(s) (w_i > 0) and lambda_i(s, a) > 0,
        #   Q_tot = sum_i W_i(maxQ_i) + sum_i lambda_i(s, a) (W_i(Q_i) - W_i(maxQ_i))
        #         = sum_i (w_i maxQ_i + v_i) + sum_i lambda_i w_i (Q_i - maxQ_i).
        w = mixer.hyper_w(state).abs() + 1e-10  # [1, N]
        v = mixer.hyper_v(state)
        lam = mixer.advantage_weights(state.expand(len(joint), -1), one_hot.flatten(1))  # [M, N]
        assert (w > 0).all() and (lam > 0).all()
        expected = (w * best + v).sum(-1) + (lam * w * (chosen - best)).sum(-1)
        torch.testing.assert_close(q_tot, expected, rtol=1e-5, atol=1e-4)
        torch.testing.assert_close(q_tot[top], (w * q.max(-1).values + v).sum())


def test_qplex_gradient_reaches_agents_through_the_value_stream_only() -> None:
    """pymarl's ``is_stop_gradient``: the advantage stream detaches ``Q_i - maxQ_i``, so dQ_tot/dQ_i = w_i."""
    torch.manual_seed(0)
    mixer = DMAQMixer((STATE_DIM,), N_AGENTS, N_ACTIONS, hypernet_embed=16)
    chosen = torch.randn(6, N_AGENTS, 1, requires_grad=True)
    state = torch.randn(6, STATE_DIM)
    one_hot = F.one_hot(torch.randint(N_ACTIONS, (6, N_AGENTS)), N_ACTIONS).float()
    best = chosen.detach() + torch.rand(6, N_AGENTS, 1)
    (grad,) = torch.autograd.grad(mixer(chosen, state, one_hot, best).sum(), chosen)
    torch.testing.assert_close(grad.squeeze(-1), mixer.hyper_w(state).abs().detach() + 1e-10)


def test_qplex_keeps_any_batch_shape() -> None:
    mixer = DMAQMixer((STATE_DIM,), N_AGENTS, N_ACTIONS)
    B = (2, 3, 4)
    one_hot = F.one_hot(torch.randint(N_ACTIONS, (*B, N_AGENTS)), N_ACTIONS).float()
    chosen = torch.randn(*B, N_AGENTS, 1)
    flat = mixer(chosen.flatten(0, 2), torch.ones(24, STATE_DIM), one_hot.flatten(0, 2), chosen.flatten(0, 2))
    out = mixer(chosen, torch.ones(*B, STATE_DIM), one_hot, chosen)
    assert out.shape == (*B, 1)
    torch.testing.assert_close(out.flatten(0, 2), flat)


def test_qplex_refuses_wrong_inputs_with_clear_errors() -> None:
    mixer = DMAQMixer((STATE_DIM,), N_AGENTS, N_ACTIONS)
    chosen, state = torch.zeros(4, N_AGENTS, 1), torch.zeros(4, STATE_DIM)
    one_hot, best = torch.zeros(4, N_AGENTS, N_ACTIONS), torch.zeros(4, N_AGENTS, 1)
    with pytest.raises(ValueError, match=r"takes 4 inputs.*got 2"):
        mixer(chosen, state)
    with pytest.raises(ValueError, match=r"takes 4 inputs.*got 5"):
        mixer(chosen, state, one_hot, best, best)
    with pytest.raises(ValueError, match="state ending in"):
        mixer(chosen, torch.zeros(4, STATE_DIM + 1), one_hot, best)
    with pytest.raises(ValueError, match="chosen_action_value of shape"):
        mixer(torch.zeros(4, N_AGENTS + 1, 1), state, one_hot, best)
    with pytest.raises(ValueError, match="action_one_hot of shape"):
        mixer(chosen, state, torch.zeros(4, N_AGENTS, N_ACTIONS + 1), best)
    with pytest.raises(ValueError, match="max_action_value of shape"):
        mixer(chosen, state, one_hot, torch.zeros(4, N_AGENTS, 2))


def test_qplex_refuses_mismatched_batch_shapes() -> None:
    """A [T, B] / [B, T] mix-up must fail, not pair rows silently or broadcast."""
    mixer = DMAQMixer((STATE_DIM,), N_AGENTS, N_ACTIONS)
    chosen, one_hot = torch.zeros(4, N_AGENTS, 1), torch.zeros(4, N_AGENTS, N_ACTIONS)
    with pytest.raises(ValueError, match="batch dims"):
        mixer(chosen, torch.zeros(2, 2, STATE_DIM), one_hot, chosen)
    with pytest.raises(ValueError, match="max_action_value of shape"):
        mixer(chosen, torch.zeros(4, STATE_DIM), one_hot, torch.zeros(1, N_AGENTS, 1))


# ---------------------------------------------------------------------------------------------- keys
@pytest.mark.parametrize("name", ["vdn", "qmix", "qplex"])
def test_mixer_module_reads_the_documented_keys(name: str) -> None:
    mixer = make_mixer(name, N_AGENTS, (STATE_DIM,), N_ACTIONS, mixing_embed_dim=8, hypernet_embed=16)
    documented = {
        "vdn": [("agents", "chosen_action_value")],
        "qmix": [("agents", "chosen_action_value"), "state"],
        "qplex": [
            ("agents", "chosen_action_value"),
            "state",
            ("agents", "action_one_hot"),
            ("agents", "max_action_value"),
        ],
    }[name]
    assert mixer_in_keys(mixer) == documented
    assert mixer_module(mixer).in_keys == documented
    assert mixer_module(mixer).out_keys == ["chosen_action_value"]

    # Another task's keys: group "players", state "global_state"; the module must read exactly those.
    module = mixer_module(mixer, group="players", state_key="global_state")
    B = 5
    chosen = torch.randn(B, N_AGENTS, 1)
    one_hot = F.one_hot(torch.randint(N_ACTIONS, (B, N_AGENTS)), N_ACTIONS).float()
    best = chosen + torch.rand(B, N_AGENTS, 1)
    state = torch.randn(B, STATE_DIM)
    players = {"chosen_action_value": chosen, "action_one_hot": one_hot, "max_action_value": best}
    td = TensorDict({"players": TensorDict(players, [B, N_AGENTS]), "global_state": state}, [B])
    out = module(td)
    args = {"vdn": (chosen,), "qmix": (chosen, state), "qplex": (chosen, state, one_hot, best)}[name]
    torch.testing.assert_close(out.get("chosen_action_value"), mixer(*args))
    assert out.get("chosen_action_value").shape == (B, 1)
