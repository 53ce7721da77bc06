"""The episodic-memory terms of the loss (eq. 32, EMU's incentive) and EMC's curiosity, on hand-built
batches: the constant-Q VDN loss of test_loss has Q_tot(s_t, a_t) = ONLINE[a0] + ONLINE[a1] and a
bootstrap value Q_tot_target(s_{t+1}) = 2 * TARGET[1] = 0 at every state."""

from __future__ import annotations

import pytest
import torch
from torchrl.modules.models.multiagent import VDNMixer

from mcrs.models.agent import RecurrentAgent
from mcrs.objectives import ValueFactorisationLoss
from mcrs.objectives.curiosity import EMCCuriosity
from mcrs.objectives.incentive import make_incentive
from tests.test_loss import TARGET, constant_q_loss, episodes

GAMMA = 0.5


def with_memory(batch, returns: list[float], hits: list[bool], ratios: list[float] | None = None):
    """Attach memory look-ups (row t: the memory of s_{t+1}) as EpisodicLookup does."""
    T = len(returns)
    batch.set("memory_return", torch.tensor([[*returns, 0.0]]).unsqueeze(-1))
    batch.set("memory_hit", torch.tensor([[*hits, False]]))
    if ratios is not None:
        batch.set("memory_ratio", torch.tensor([[*ratios, 0.0]]).unsqueeze(-1))
    assert batch.batch_size[1] == T + 1
    return batch


def loss_with(memory_weight: float = 0.0, incentive: str = "none") -> ValueFactorisationLoss:
    loss = constant_q_loss(gamma=GAMMA)
    loss.memory_weight, loss.incentive = memory_weight, make_incentive(incentive)
    return loss


def test_memory_target_is_reward_plus_gamma_h_on_hits_and_nothing_on_misses() -> None:
    actions = torch.tensor([[[0, 3], [1, 1], [2, 0]]])  # Q_tot = -1, 10, 1
    rewards = torch.tensor([[2.0, 1.0, -1.0]])
    q_tot = torch.tensor([-1.0, 10.0, 1.0])
    returns, hits = [6.0, 100.0, 4.0], [True, False, True]
    batch = with_memory(episodes(3, actions, rewards), returns, hits)
    out = loss_with(memory_weight=0.1)(batch)
    plain = loss_with()(batch)
    memory_target = rewards[0] + GAMMA * torch.tensor(returns)
    expected = ((q_tot - memory_target) ** 2 * torch.tensor(hits)).sum() / 3  # mean over valid transitions
    assert out["loss_memory"].item() == pytest.approx(expected.item())
    assert out["loss"].item() == pytest.approx(plain["loss"].item() + 0.1 * expected.item())
    assert out["memory_hit_rate"].item() == pytest.approx(2 / 3)
    # A miss contributes nothing, whatever H says there.
    batch.get("memory_return")[0, 1] = -1e6
    assert loss_with(memory_weight=0.1)(batch)["loss"].item() == pytest.approx(out["loss"].item())
    # No memory term for the padding row or without weight.
    assert not {"loss_memory", "memory_hit_rate", "memory_target_mean"} & set(plain.keys())


def test_memory_term_gradient_pulls_q_tot_towards_the_memory_target() -> None:
    batch = with_memory(episodes(1, torch.tensor([[[0, 3]]]), torch.tensor([[0.0]])), [50.0], [True])
    loss = loss_with(memory_weight=1.0)
    loss(batch)["loss"].backward()
    grad_with = loss.agent_network.fc2.bias.grad.clone()
    loss.agent_network.fc2.bias.grad = None
    batch.set("memory_hit", torch.zeros(1, 2, dtype=torch.bool))
    loss(batch)["loss"].backward()
    grad_without = loss.agent_network.fc2.bias.grad.clone()
    # Q_tot(-1) is far below the memory target 25: the extra gradient on the taken actions is negative
    # (descending it raises their Q) and -2 * (25 - (-1)) = -52 per agent.
    extra = grad_with - grad_without
    assert extra[0].item() == pytest.approx(-52.0) and extra[3].item() == pytest.approx(-52.0)
    assert extra[1].item() == 0.0 and extra[2].item() == 0.0


class RecordingLoss(ValueFactorisationLoss):
    """Records the reward that reaches the TD target."""

    def targets(self, reward, next_value, done, terminated):
        self.seen_reward, self.seen_next = reward.clone(), next_value.clone()
        return super().targets(reward, next_value, done, terminated)


def recording_loss(incentive: str) -> RecordingLoss:
    base = constant_q_loss(gamma=GAMMA)
    loss = RecordingLoss(base.agent_network, VDNMixer(2, "cpu"), gamma=GAMMA, incentive=incentive)
    with torch.no_grad():
        loss.target_agent_network_params["fc2", "bias"].copy_(TARGET)
    return loss


def test_emu_incentive_on_a_hand_built_case() -> None:
    actions = torch.tensor([[[0, 3], [1, 1], [2, 0]]])
    rewards = torch.tensor([[2.0, 1.0, -1.0]])
    batch = with_memory(episodes(3, actions, rewards), [4.0, -3.0, 8.0], [True, True, False], [0.5, 1.0, 1.0])
    loss = recording_loss("fixed")
    loss(batch)
    assert torch.equal(loss.seen_next, torch.full((1, 3, 1), 2 * TARGET[1].item()))  # Q_target(s') = 0
    # r_p = gamma * ratio * max(H - Q_target(s'), 0) on hits: 0.5 * 0.5 * 4 = 1; H below Q: 0; a miss: 0.
    assert loss.seen_reward[0, :, 0].tolist() == pytest.approx([2.0 + 1.0, 1.0, -1.0])
    change = recording_loss("change")  # EMU-change drops the ratio: 0.5 * 4 = 2
    change(batch)
    assert change.seen_reward[0, :, 0].tolist() == pytest.approx([2.0 + 2.0, 1.0, -1.0])
    assert "memory_ratio" in loss.in_keys and "memory_ratio" not in change.in_keys


def test_intrinsic_reward_enters_the_td_target_only() -> None:
    batch = episodes(2, torch.tensor([[[0, 3], [1, 1]]]), torch.tensor([[2.0, 1.0]]))
    batch.set("intrinsic_reward", torch.tensor([[[0.25], [0.5], [9.0]]]))  # the last row is padding
    loss = recording_loss("none")
    out = loss(batch)
    assert loss.seen_reward[0, :, 0].tolist() == pytest.approx([2.25, 1.5])
    assert out["intrinsic_mean"].item() == pytest.approx(0.375)


def test_bad_memory_arguments_are_refused() -> None:
    agent = RecurrentAgent(3, 4, 2, 4)
    with pytest.raises(ValueError, match="memory_weight must be >= 0"):
        ValueFactorisationLoss(agent, VDNMixer(2, "cpu"), memory_weight=-0.1)
    with pytest.raises(ValueError, match="incentive must be one of none, fixed, change"):
        ValueFactorisationLoss(agent, VDNMixer(2, "cpu"), incentive="always")


def memory_loss_in_units(scale: float) -> ValueFactorisationLoss:
    """EMU's loss with the memory term, its networks' outputs ``scale`` times test_loss's constants."""
    loss = loss_with(memory_weight=0.1, incentive="fixed")
    loss.reward_scale = scale
    with torch.no_grad():
        loss.agent_network.fc2.bias.mul_(scale)
        loss.target_agent_network_params["fc2", "bias"].mul_(scale)
    return loss


@pytest.mark.parametrize("scale", [0.01, 3.0])
def test_reward_scale_is_a_change_of_units_for_the_reward_the_memory_and_the_incentive(scale: float) -> None:
    actions = torch.tensor([[[0, 3], [1, 1], [2, 0]]])
    batch = with_memory(
        episodes(3, actions, torch.tensor([[2.0, 1.0, -1.0]])),
        [40.0, -3.0, 8.0], [True, True, False], [0.5, 1.0, 1.0],
    )  # fmt: skip
    unit, scaled = memory_loss_in_units(1.0)(batch), memory_loss_in_units(scale)(batch)
    # Networks that learned scale x the values see every target scale x: the losses scale by scale^2 ...
    for key in ("loss", "loss_td", "loss_memory"):
        assert scaled[key].item() == pytest.approx(scale**2 * unit[key].item(), rel=1e-5)
    # ... and the logged values are in the env's units, the same as at scale 1.
    for key in ("q_taken_mean", "target_mean", "td_error_abs", "memory_target_mean", "incentive_mean"):
        assert scaled[key].item() == pytest.approx(unit[key].item(), rel=1e-5)
    assert unit["incentive_mean"].item() > 0  # the incentive is in play (H above Q_target on a hit)


def test_reward_scale_leaves_the_intrinsic_reward_unscaled_and_refuses_bad_values() -> None:
    batch = episodes(2, torch.tensor([[[0, 3], [1, 1]]]), torch.tensor([[2.0, 1.0]]))
    batch.set("intrinsic_reward", torch.tensor([[[0.25], [0.5], [9.0]]]))
    loss = recording_loss("none")
    loss.reward_scale = 0.1
    loss(batch)
    assert loss.seen_reward[0, :, 0].tolist() == pytest.approx([0.2 + 0.25, 0.1 + 0.5])
    agent = RecurrentAgent(3, 4, 2, 4)
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="reward_scale must be a finite number > 0"):
            ValueFactorisationLoss(agent, VDNMixer(2, "cpu"), reward_scale=bad)


def curiosity(scale: float = 0.001) -> EMCCuriosity:
    torch.manual_seed(0)
    return EMCCuriosity(RecurrentAgent(3, 4, 2, 8), gamma=GAMMA, scale=scale, decay_rate=0.9, decay_cycle=100)


def test_curiosity_scale_decays_by_the_rate_every_cycle() -> None:
    c = curiosity(0.001)
    assert c.set_env_steps(0) == pytest.approx(0.001)
    assert c.set_env_steps(99) == pytest.approx(0.001)
    assert c.set_env_steps(100) == pytest.approx(0.0009)
    assert c.set_env_steps(250) == pytest.approx(0.001 * 0.9**2)


def test_curiosity_reward_is_the_scaled_prediction_error_at_the_next_step_and_the_predictor_learns() -> None:
    c = curiosity(0.5)
    torch.manual_seed(1)
    batch = episodes(4, torch.randint(0, 4, (1, 4, 2)), torch.randn(1, 4))
    inputs = c.vdn_loss.agent_inputs(batch)
    with torch.no_grad():
        target_before = c.vdn_loss.agent_values(batch, target=True, inputs=inputs)
    intrinsic, stats = c.update(batch, step=0)
    assert intrinsic.shape == (1, 5, 1) and intrinsic[0, -1].item() == 0.0
    # The VDN learner stepped and its soft target moved by tau only.
    with torch.no_grad():
        target_after = c.vdn_loss.agent_values(batch, target=True, inputs=inputs)
    assert 0 < (target_after - target_before).abs().max() < 0.05
    # The reward of transition t is scale * mean over agents of ||predictor(t+1) - 10 * target(t+1)||, whose
    # mean over valid transitions is the predictor's loss.
    assert stats["curiosity_loss_prediction"].item() == pytest.approx(intrinsic[0, :-1].mean().item() / 0.5)
    errors = [c.update(batch, step=0)[1]["curiosity_loss_prediction"].item() for _ in range(200)]
    assert errors[-1] < 0.5 * errors[0]
