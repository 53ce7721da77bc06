"""EMC's curiosity after the speed work computes what the implementations before it computed.

The references below are faithful copies of the computation as it was: ``EMCCuriosity.update`` op for op
(agent inputs built twice, every unroll through ``nn.GRU``), with either the first unroll (the output layer
on the permuted GRU output) or the one before ``mcrs.models.gru`` (``fused_cpu_gru`` off). Both start from
the same weights and optimiser states and take the same fixed batches; the intrinsic rewards, the statistics
and every parameter must agree after each update to float rounding (rtol 1e-5, atol 1e-6 for the intrinsic
rewards and statistics, rtol 1e-5, atol 1e-7 for the parameters: the GRU now sums in another order), far
below the 5e-4 an optimiser step moves a weight.
"""

from __future__ import annotations

import pytest
import torch
from mcrs_benchmarks.learner import synthetic_episodes
from tensordict import TensorDictBase
from torch.nn import functional as F

from mcrs.env.config import from_mapping
from mcrs.env.core import N_ACTIONS
from mcrs.models.agent import RecurrentAgent
from mcrs.objectives.curiosity import PREDICTION_SCALE, EMCCuriosity
from mcrs.objectives.gradient import gradient_step


def reference_unroll(agent: RecurrentAgent, inputs: torch.Tensor) -> torch.Tensor:
    """``RecurrentAgent.unroll`` before the change: fc2 applied to the permuted ``[B, T, N, H]`` output."""
    B, T, N, _ = inputs.shape
    x = F.relu(agent.fc1(inputs)).permute(0, 2, 1, 3).reshape(B * N, T, agent.hidden_dim)
    out, _ = agent.rnn(x)
    return agent.fc2(out.reshape(B, N, T, agent.hidden_dim).permute(0, 2, 1, 3))


class ReferenceAgent(RecurrentAgent):
    def unroll(self, inputs: torch.Tensor) -> torch.Tensor:
        return reference_unroll(self, inputs)


def reference_update(c: EMCCuriosity, episodes: TensorDictBase, step: int) -> tuple[torch.Tensor, dict]:
    """``EMCCuriosity.update`` as it was, on modules whose agents unroll the old way."""
    vdn = c.vdn_loss(episodes)
    gradient_step(vdn["loss"], c.vdn_optimizer, c.vdn_params, c.grad_clip, step, "curiosity_vdn")
    c.soft_update.step()
    inputs = c.vdn_loss.agent_inputs(episodes)
    target = c.vdn_loss.agent_values(episodes, target=True, inputs=inputs) * PREDICTION_SCALE
    error = (c.predictor.unroll(inputs) - target).norm(dim=-1)
    filled = episodes.get(c.vdn_loss.tensor_keys.filled)[:, :-1]
    valid = filled.unsqueeze(-1).to(error.dtype)
    next_error = error[:, 1:]
    n = (valid.sum() * error.shape[-1]).clamp(min=1.0)
    prediction_loss = (next_error * valid).sum() / n
    gradient_step(prediction_loss, c.predictor_optimizer, c.predictor_params, c.grad_clip, step, "p")
    intrinsic = torch.zeros_like(error[..., :1])
    intrinsic[:, :-1] = c.scale * next_error.detach().mean(-1, keepdim=True) * valid
    return intrinsic, {"curiosity_loss_vdn": vdn["loss_td"], "curiosity_loss_prediction": prediction_loss}


def test_unroll_equals_the_previous_layout() -> None:
    torch.manual_seed(0)
    agent = RecurrentAgent(7, N_ACTIONS, 3, 16)
    inputs = torch.randn(4, 9, 3, agent.input_dim)
    torch.testing.assert_close(agent.unroll(inputs), reference_unroll(agent, inputs), rtol=0, atol=0)


@pytest.mark.parametrize("reference_unroll", ["first", "nn_gru"])
def test_curiosity_equals_the_previous_implementations_on_fixed_batches(reference_unroll: str) -> None:
    env_config = from_mapping({"name": "map10", "max_steps": 12})

    def build() -> EMCCuriosity:  # the same weights twice (a deepcopy would untie TorchRL's parameters)
        torch.manual_seed(0)
        agent = RecurrentAgent(env_config.obs_dim, N_ACTIONS, env_config.n_uavs, 32)
        return EMCCuriosity(agent, scale=0.5)

    ours, reference = build(), build()
    for module in (reference.vdn_loss.agent_network, reference.predictor):
        module.fused_cpu_gru = False
        if reference_unroll == "first":
            module.__class__ = ReferenceAgent
    generator = torch.Generator().manual_seed(1)
    batches = [synthetic_episodes(6, env_config, generator) for _ in range(6)]
    for step, batch in enumerate(batches):
        intrinsic, stats = ours.update(batch.clone(), step)
        expected, expected_stats = reference_update(reference, batch.clone(), step)
        assert intrinsic.abs().sum() > 0
        torch.testing.assert_close(intrinsic, expected, rtol=1e-5, atol=1e-6)
        for key, value in expected_stats.items():
            torch.testing.assert_close(stats[key], value.detach(), rtol=1e-5, atol=1e-6)
        for (name, value), (_, old) in zip(
            ours.state_dict().items(), reference.state_dict().items(), strict=True
        ):
            torch.testing.assert_close(value, old, rtol=1e-5, atol=1e-7, msg=name)
