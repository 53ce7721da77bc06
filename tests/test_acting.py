"""The acting policy: masked epsilon-greedy, the closed-form schedule and the carried recurrent state."""

from __future__ import annotations

import pytest
import torch
from torchrl.collectors import Collector
from torchrl.envs import TransformedEnv, check_env_specs
from torchrl.envs.utils import ExplorationType, set_exploration_type

from mcrs.env import MCRSEnv
from mcrs.models.acting import make_acting_policy, recurrent_primer
from mcrs.models.agent import RecurrentAgent


def make(num_envs: int = 6, invalid_action: str = "raise", **eps):
    env = MCRSEnv("map10", num_envs=num_envs, max_steps=12, invalid_action=invalid_action)
    cfg = env.config
    agent = RecurrentAgent(cfg.obs_dim, 8, cfg.n_uavs, hidden_dim=16)
    env = TransformedEnv(env, recurrent_primer(num_envs, cfg.n_uavs, 16))
    greedy, exploring, epsilon = make_acting_policy(agent, 8, **eps)
    return env, agent, greedy, exploring, epsilon


def test_primed_env_passes_torchrl_checks() -> None:
    # check_env_specs draws random actions from the transformed env's (cached, unmasked) action spec.
    env, *_ = make(invalid_action="clip")
    check_env_specs(env)


@pytest.mark.parametrize("eps", [0.0, 1.0])
def test_masked_actions_are_never_chosen(eps: float) -> None:
    torch.manual_seed(0)
    env, _, _, exploring, _ = make(eps_start=eps, eps_end=eps)
    rollout = env.rollout(12, exploring)
    mask, action = rollout["agents", "action_mask"], rollout["agents", "action"]
    assert mask.gather(-1, action.unsqueeze(-1)).all()
    assert (~mask).any()  # the test means something: some moves were forbidden (grid edges)


def test_greedy_action_is_the_masked_argmax() -> None:
    env, _, greedy, *_ = make()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        rollout = env.rollout(12, greedy)
    q = rollout["agents", "action_value"]
    masked = q.masked_fill(~rollout["agents", "action_mask"], float("-inf"))
    assert torch.equal(rollout["agents", "action"], masked.argmax(-1))


def test_epsilon_schedule_is_linear_then_flat() -> None:
    *_, epsilon = make(eps_start=1.0, eps_end=0.05, eps_anneal_steps=1000)
    assert epsilon.set_env_steps(0) == pytest.approx(1.0)
    assert epsilon.set_env_steps(500) == pytest.approx(0.525)
    assert epsilon.set_env_steps(10_000) == pytest.approx(0.05)
    assert float(epsilon.eps) == pytest.approx(0.05)


def test_exploration_rate_follows_epsilon() -> None:
    torch.manual_seed(0)
    env, _, _, exploring, epsilon = make(num_envs=64)
    epsilon.set_env_steps(0)  # eps = 1: uniform among allowed moves
    rollout = env.rollout(12, exploring)
    q = rollout["agents", "action_value"].masked_fill(~rollout["agents", "action_mask"], float("-inf"))
    greedy_share = (rollout["agents", "action"] == q.argmax(-1)).float().mean().item()
    assert greedy_share < 0.4  # ~1/(allowed moves) when acting at random
    epsilon.eps.fill_(0.0)
    rollout = env.rollout(12, exploring)
    q = rollout["agents", "action_value"].masked_fill(~rollout["agents", "action_mask"], float("-inf"))
    assert torch.equal(rollout["agents", "action"], q.argmax(-1))


def test_recurrent_state_is_carried_and_reset_between_episodes() -> None:
    env, agent, _, exploring, _ = make(num_envs=2)
    collector = Collector(
        env, exploring, frames_per_batch=2 * 12, total_frames=-1, trust_policy=True,
        auto_register_policy_transforms=False,
    )  # fmt: skip
    batch = next(iter(collector))
    hidden, nxt = batch["agents", "rnn_hidden"], batch["next", "agents", "rnn_hidden"]
    assert torch.equal(hidden[:, 1:], nxt[:, :-1])  # step t+1 starts from step t's output
    assert (batch["agents", "last_action"][:, 1:] == batch["agents", "action"][:, :-1]).all()
    # The same episode replayed in one unroll from a zero state gives the collector's values.
    last_action = batch["agents", "last_action"].masked_fill(batch["step_count"] == 0, -1)
    inputs = agent.build_inputs(batch["agents", "observation"], last_action)
    with torch.no_grad():
        q = agent.unroll(inputs)
    allowed = batch["agents", "action_mask"]  # QValueModule writes masked values for forbidden moves
    torch.testing.assert_close(q[allowed], batch["agents", "action_value"][allowed], rtol=1e-5, atol=1e-5)
    collector.shutdown()
