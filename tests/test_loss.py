"""The value-factorisation loss: double-Q targets, masking, TD(lambda) and padding on hand-built batches."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.modules.models.multiagent import VDNMixer

from mcrs.models.agent import RecurrentAgent
from mcrs.models.mixers import make_mixer
from mcrs.objectives import ValueFactorisationLoss

A, N = 4, 2
ONLINE = torch.tensor([0.0, 5.0, 1.0, -1.0])  # online net: best is 1, then 2
TARGET = torch.tensor([10.0, 0.0, 3.0, 7.0])  # target net: best is 0


def constant_q_loss(
    double_q: bool = True, td_lambda: float = 0.0, gamma: float = 0.5
) -> ValueFactorisationLoss:
    """A VDN loss whose agents output the same Q for every input: ONLINE (online net), TARGET (target net)."""
    agent = RecurrentAgent(obs_dim=3, n_actions=A, n_agents=N, hidden_dim=4)
    with torch.no_grad():
        agent.fc2.weight.zero_()
        agent.fc2.bias.copy_(ONLINE)
    loss = ValueFactorisationLoss(
        agent, VDNMixer(N, "cpu"), gamma=gamma, td_lambda=td_lambda, double_q=double_q
    )
    with torch.no_grad():
        loss.target_agent_network_params["fc2", "bias"].copy_(TARGET)
    return loss


def episodes(
    T: int, actions: torch.Tensor, rewards: torch.Tensor, mask: torch.Tensor | None = None
) -> TensorDict:
    """One episode of T transitions in the episode layout [1, T+1]."""
    mask = torch.ones(1, T + 1, N, A, dtype=torch.bool) if mask is None else mask
    filled = torch.ones(1, T + 1, dtype=torch.bool)
    filled[:, -1] = False
    done = torch.zeros(1, T + 1, 1, dtype=torch.bool)
    done[:, T - 1] = True
    return TensorDict(
        {
            ("agents", "observation"): torch.randn(1, T + 1, N, 3),
            ("agents", "action_mask"): mask,
            ("agents", "action"): torch.cat([actions, torch.zeros(1, 1, N, dtype=torch.long)], 1),
            "state": torch.randn(1, T + 1, 5),
            "reward": torch.cat([rewards, torch.zeros(1, 1)], 1).unsqueeze(-1),
            "done": done,
            "terminated": torch.zeros(1, T + 1, 1, dtype=torch.bool),
            "filled": filled,
        },
        batch_size=[1, T + 1],
    )


def test_double_q_target_uses_online_argmax_and_target_value() -> None:
    actions = torch.tensor([[[0, 3]]])  # one transition
    batch = episodes(1, actions, torch.tensor([[2.0]]))
    out = constant_q_loss(double_q=True)(batch)
    q_taken = ONLINE[0] + ONLINE[3]  # -1
    y = 2.0 + 0.5 * (TARGET[1] + TARGET[1])  # online argmax is 1 for both agents; valued by the target net
    assert out["q_taken_mean"].item() == pytest.approx(q_taken.item())
    assert out["target_mean"].item() == pytest.approx(y.item())
    assert out["loss"].item() == pytest.approx(((q_taken - y) ** 2).item())


def test_plain_q_target_uses_target_argmax() -> None:
    batch = episodes(1, torch.tensor([[[0, 3]]]), torch.tensor([[2.0]]))
    out = constant_q_loss(double_q=False)(batch)
    assert out["target_mean"].item() == pytest.approx(2.0 + 0.5 * 2 * TARGET[0].item())


@pytest.mark.parametrize("double_q", [True, False])
def test_masked_actions_never_enter_the_target(double_q: bool) -> None:
    mask = torch.ones(1, 2, N, A, dtype=torch.bool)
    mask[0, 1, 0, 1] = False  # agent 0 may not take the online favourite at the next step
    mask[0, 1, 0, 0] = False  # nor the target favourite
    mask[0, 1, 1, [0, 1]] = False
    out = constant_q_loss(double_q=double_q)(
        episodes(1, torch.tensor([[[0, 0]]]), torch.tensor([[0.0]]), mask)
    )
    # Allowed next actions are {2, 3} for both agents: double Q picks online's 2; plain Q picks target's 3.
    expected = 2 * (TARGET[2] if double_q else TARGET[3])
    assert out["target_mean"].item() == pytest.approx(0.5 * expected.item())


def test_td_lambda_matches_the_recursion() -> None:
    T, gamma, lam = 4, 0.9, 0.6
    rewards = torch.tensor([[1.0, -2.0, 0.5, 3.0]])
    batch = episodes(T, torch.zeros(1, T, N, dtype=torch.long), rewards)
    out = constant_q_loss(td_lambda=lam, gamma=gamma)(batch)
    v = 2 * TARGET[1].item()  # every next-state value (double Q, constant nets)
    G = [0.0] * T
    G[T - 1] = rewards[0, T - 1].item() + gamma * v  # the last transition bootstraps (time limit)
    for t in reversed(range(T - 1)):
        G[t] = rewards[0, t].item() + gamma * ((1 - lam) * v + lam * G[t + 1])
    assert out["target_mean"].item() == pytest.approx(sum(G) / T, rel=1e-5)


def test_terminated_transition_does_not_bootstrap() -> None:
    batch = episodes(1, torch.tensor([[[0, 0]]]), torch.tensor([[4.0]]))
    batch["terminated"][:, 0] = True
    assert constant_q_loss()(batch)["target_mean"].item() == pytest.approx(4.0)


def test_padding_is_ignored() -> None:
    rewards = torch.tensor([[1.0, 1000.0]])
    batch = episodes(2, torch.zeros(1, 2, N, dtype=torch.long), rewards)
    batch["filled"][:, 1] = False  # the second transition is padding
    batch["terminated"][:, 0] = True
    out = constant_q_loss()(batch)
    assert out["target_mean"].item() == pytest.approx(1.0)


@pytest.mark.parametrize("mixer", ["qmix", "vdn", "qplex"])
def test_gradients_reach_online_parameters_only(mixer: str) -> None:
    torch.manual_seed(0)
    agent = RecurrentAgent(obs_dim=3, n_actions=A, n_agents=N, hidden_dim=8)
    loss = ValueFactorisationLoss(agent, make_mixer(mixer, N, (5,), A, mixing_embed_dim=4, hypernet_embed=8))
    batch = episodes(3, torch.randint(0, A, (1, 3, N)), torch.randn(1, 3))
    out = loss(batch)
    out["loss"].backward()
    assert torch.isfinite(out["loss"])
    assert all(p.grad is not None for p in agent.parameters())
    targets = [
        *loss.target_agent_network_params.values(True, True),
        *loss.target_mixer_params.values(True, True),
    ]
    assert targets and all(not t.requires_grad for t in targets)
    online = dict(loss.agent_network_params.items(True, True))
    assert not torch.equal(online["fc1", "weight"].data, online["fc1", "weight"].data + 1)  # sanity
    assert not loss.target_agent_network_params["fc1", "weight"].is_set_to(agent.fc1.weight.data)


def test_bad_hyper_parameters_are_refused() -> None:
    agent = RecurrentAgent(obs_dim=3, n_actions=A, n_agents=N)
    with pytest.raises(ValueError, match="td_lambda"):
        ValueFactorisationLoss(agent, VDNMixer(N, "cpu"), td_lambda=1.5)
    with pytest.raises(ValueError, match="gamma"):
        ValueFactorisationLoss(agent, VDNMixer(N, "cpu"), gamma=-0.1)


def test_unroll_equals_step_by_step() -> None:
    torch.manual_seed(1)
    agent = RecurrentAgent(obs_dim=3, n_actions=A, n_agents=N, hidden_dim=8)
    x = agent.build_inputs(torch.randn(2, 5, N, 3), torch.randint(-1, A, (2, 5, N)))
    unrolled = agent.unroll(x)
    h = torch.zeros(2, N, 8)
    for t in range(5):
        q, h = agent.step(x[:, t], h)
        torch.testing.assert_close(q, unrolled[:, t])


def test_build_inputs_one_hots() -> None:
    agent = RecurrentAgent(obs_dim=2, n_actions=3, n_agents=2)
    x = agent.build_inputs(torch.zeros(1, 2, 2), torch.tensor([[-1, 2]]))
    assert x.shape == (1, 2, 2 + 3 + 2)
    torch.testing.assert_close(x[0, 0, 2:5], torch.zeros(3))  # no previous action at the first step
    torch.testing.assert_close(x[0, 1, 2:5], torch.tensor([0.0, 0.0, 1.0]))
    torch.testing.assert_close(x[0, :, 5:], torch.eye(2))


def test_target_parameters_survive_forward() -> None:
    """Regression: swapping the target parameters into the module must not swap the online ones back."""
    loss = constant_q_loss()
    batch = episodes(1, torch.tensor([[[0, 3]]]), torch.tensor([[2.0]]))
    first = loss(batch)["target_mean"].item()
    for _ in range(2):
        assert loss(batch)["target_mean"].item() == first
    torch.testing.assert_close(loss.target_agent_network_params["fc2", "bias"], TARGET)
    assert loss.agent_network.fc2.bias is loss.agent_network_params["fc2", "bias"]
