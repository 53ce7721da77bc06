"""``gru_sequence`` computes what ``nn.GRU`` computes on the CPU, to float rounding: the forward pass runs
ATen's operations in ATen's order but the input-gate GEMM one step at a time, the backward pass sums in
another order. Tolerances: rtol 1e-5, atol 1e-6 (values and gradients are of order 0.1 to 10)."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from mcrs.models.agent import RecurrentAgent
from mcrs.models.gru import gru_sequence


def _gru(seed: int = 0, hidden: int = 16, inputs: int = 8) -> nn.GRU:
    torch.manual_seed(seed)
    return nn.GRU(inputs, hidden)


def test_forward_matches_nn_gru_with_and_without_autograd() -> None:
    gru = _gru()
    x = torch.randn(13, 7, 8)
    expected, _ = gru(x)
    torch.testing.assert_close(gru_sequence(x, gru), expected, rtol=1e-5, atol=1e-6)
    with torch.no_grad():
        torch.testing.assert_close(gru_sequence(x, gru), expected, rtol=1e-5, atol=1e-6)


def test_gradients_match_nn_gru_to_float_rounding() -> None:
    gru = _gru(1)
    x = torch.randn(11, 6, 8, requires_grad=True)
    weight = torch.randn(11, 6, 16)
    params = [x, *gru.parameters()]
    expected = torch.autograd.grad((gru(x)[0] * weight).sum(), params)
    ours = torch.autograd.grad((gru_sequence(x, gru) * weight).sum(), params)
    for got, want in zip(ours, expected, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)


def test_buffers_are_reused_safely_and_a_second_backward_is_refused() -> None:
    gru = _gru(2)
    x = torch.randn(5, 4, 8)
    first = gru_sequence(x, gru).sum()
    second = (gru_sequence(x * 2, gru) ** 2).sum()  # two live graphs: the second gets its own buffers
    grads_second = torch.autograd.grad(second, list(gru.parameters()))
    grads_first = torch.autograd.grad(first, list(gru.parameters()), retain_graph=True)
    for ours, loss in ((grads_first, gru(x)[0].sum()), (grads_second, (gru(x * 2)[0] ** 2).sum())):
        for got, want in zip(ours, torch.autograd.grad(loss, list(gru.parameters())), strict=True):
            torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
    gru_sequence(x, gru).sum().backward()  # the pool lends the first graph's buffers again
    with pytest.raises(RuntimeError, match="twice"):
        torch.autograd.grad(first, list(gru.parameters()))


def test_other_gru_shapes_are_refused() -> None:
    with pytest.raises(ValueError, match="one-layer"):
        gru_sequence(torch.randn(3, 2, 4), nn.GRU(4, 4, num_layers=2))


def test_fused_agent_unroll_matches_the_nn_gru_unroll() -> None:
    torch.manual_seed(3)
    agent = RecurrentAgent(7, 5, 3, 16)
    inputs = torch.randn(4, 9, 3, agent.input_dim)
    expected = agent.unroll(inputs)
    grads = torch.autograd.grad(expected.pow(2).sum(), list(agent.parameters()))
    agent.fused_cpu_gru = True
    q = agent.unroll(inputs)
    torch.testing.assert_close(q, expected, rtol=1e-5, atol=1e-6)
    for got, want in zip(torch.autograd.grad(q.pow(2).sum(), list(agent.parameters())), grads, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
