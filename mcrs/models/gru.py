"""A CPU GRU over whole sequences that is cheaper than ``nn.GRU``; EMC's curiosity unrolls four per update.

On CPU, ``nn.GRU`` computes the input gates of every step in one GEMM whose output leaves the cache, and
its backward pass runs one weight-gradient GEMM per step. Here the input gates are computed step by step,
the backward pass makes each weight gradient one GEMM, and large buffers are reused between calls.

The forward pass does ATen's operations in ATen's order; the backward pass sums in another order, so values
and gradients agree with ``nn.GRU`` to float rounding (``tests/test_gru.py``). A graph allows one backward
pass. It covers what :class:`RecurrentAgent` uses: time-major input ``[T, M, in]``, a zero initial state,
one layer, biases."""

from __future__ import annotations

import threading

import torch
from torch import Tensor, nn
from torch.autograd.function import once_differentiable

_pool = threading.local()  # per-thread buffers reused between calls


class _Buffers:
    """Scratch tensors of one shape, lent to one graph at a time; ``generation`` counts the lendings."""

    def __init__(self, like: Tensor, shapes: tuple[tuple[int, ...], ...]) -> None:
        self.tensors = [like.new_empty(shape) for shape in shapes]
        self.generation = 0


def _borrow(like: Tensor, shapes: tuple[tuple[int, ...], ...]) -> _Buffers:
    """Return free buffers of these shapes from this thread's pool, or new ones."""
    key = (shapes, like.dtype, like.device)
    free = getattr(_pool, "free", None)
    if free is None:
        free = _pool.free = {}
    buffers = free.pop(key, None)
    return _Buffers(like, shapes) if buffers is None else buffers


def _give_back(buffers: _Buffers) -> None:
    buffers.generation += 1
    t = buffers.tensors[0]
    _pool.free[(tuple(tuple(b.shape) for b in buffers.tensors), t.dtype, t.device)] = buffers


def gru_forward(
    x: Tensor,
    w_ih: Tensor,
    w_hh: Tensor,
    b_ih: Tensor,
    b_hh: Tensor,
    gh_all: Tensor | None = None,
    n_all: Tensor | None = None,
) -> Tensor:
    """Return the hidden states ``[T+1, M, H]``, row 0 being the zero initial state. It keeps in ``gh_all [T,
    M, 3H]`` and ``n_all [T, M, H]`` what the backward pass needs: r, z, ``W_hn h + b_hn`` and n."""
    T, M, _ = x.shape
    H = w_hh.shape[1]
    w_ih_t, w_hh_t = w_ih.t(), w_hh.t()
    hs = x.new_empty(T + 1, M, H)
    hs[0].zero_()
    gi = x.new_empty(M, 3 * H)  # per-step scratch, allocated once
    gh_scratch = x.new_empty(M, 3 * H) if gh_all is None else None
    n_scratch = x.new_empty(M, H) if n_all is None else None
    h = hs[0]
    for t in range(T):
        torch.addmm(b_ih, x[t], w_ih_t, out=gi)
        gh = torch.addmm(b_hh, h, w_hh_t, out=gh_scratch if gh_all is None else gh_all[t])
        # ATen's gru_cell, op for op: r, z = sigmoid(gh + gi); n = tanh(gh_n * r + gi_n); h = (h - n) * z + n
        rz = gh[:, : 2 * H].add_(gi[:, : 2 * H]).sigmoid_()
        n = torch.mul(gh[:, 2 * H :], rz[:, :H], out=n_scratch if n_all is None else n_all[t])
        n.add_(gi[:, 2 * H :]).tanh_()
        h = torch.sub(h, n, out=hs[t + 1]).mul_(rz[:, H:]).add_(n)
    return hs


class _GRUSequence(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: Tensor, w_ih: Tensor, w_hh: Tensor, b_ih: Tensor, b_hh: Tensor) -> Tensor:
        T, M, _ = x.shape
        H = w_hh.shape[1]
        saved = _borrow(x, ((T, M, 3 * H), (T, M, H)))
        hs = gru_forward(x, w_ih, w_hh, b_ih, b_hh, *saved.tensors)
        ctx.buffers, ctx.generation = saved, saved.generation
        ctx.save_for_backward(x, w_ih, w_hh, hs)
        return hs[1:]

    @staticmethod
    @once_differentiable
    def backward(ctx, d_out: Tensor) -> tuple[Tensor | None, ...]:
        if ctx.buffers.generation != ctx.generation:
            raise RuntimeError("gru_sequence: backward through the same graph twice is not supported")
        x, w_ih, w_hh, hs = ctx.saved_tensors
        gh_all, n_all = ctx.buffers.tensors
        T, M, H = n_all.shape
        d_out = d_out.contiguous()
        grads = _borrow(d_out, ((T, M, 3 * H), (T, M, H)))
        # Gradients of W_hh h + b_hh (its r, z and n parts) and of the n gate's pre-activation.
        dgh_all, dn_all = grads.tensors
        dh = d_out[T - 1].clone()
        dh_z, tmp = torch.empty_like(dh), torch.empty_like(dh)  # per-step scratch, allocated once
        for t in reversed(range(T)):
            if t < T - 1:
                dh.add_(d_out[t])
            gh, n, dgh = gh_all[t], n_all[t], dgh_all[t]
            r, z, gh_n = gh[:, :H], gh[:, H : 2 * H], gh[:, 2 * H :]
            # h_t = (h_{t-1} - n) * z + n: the pre-activation gradients of z, n and r, then dh_{t-1}
            torch.mul(dh, z, out=dh_z)
            dz = torch.sub(hs[t], n, out=dgh[:, H : 2 * H]).mul_(dh)
            dz.mul_(torch.addcmul(z, z, z, value=-1, out=tmp))  # sigmoid' = z - z^2
            dn = torch.mul(n, n, out=dn_all[t]).neg_().add_(1).mul_(dh.sub_(dh_z))
            torch.mul(dn, gh_n, out=dgh[:, :H]).mul_(torch.addcmul(r, r, r, value=-1, out=tmp))
            torch.mul(dn, r, out=dgh[:, 2 * H :])
            torch.addmm(dh_z, dgh, w_hh, out=dh)
        _give_back(ctx.buffers)
        dgh, dn = dgh_all.view(T * M, 3 * H), dn_all.view(T * M, H)
        dgi_rz = dgh[:, : 2 * H]  # the r and z gates see gi + gh: the same gradient
        dx = None
        if ctx.needs_input_grad[0]:
            dx = (dn @ w_ih[2 * H :]).addmm_(dgi_rz, w_ih[: 2 * H]).view(x.shape)
        xs, h_prev = x.reshape(T * M, -1), hs[:-1].reshape(T * M, H)
        dw_ih = torch.cat([dgi_rz.t() @ xs, dn.t() @ xs])
        db_hh = dgh.sum(0)
        db = torch.cat([db_hh[: 2 * H], dn.sum(0)]), db_hh
        dw_hh = dgh.t() @ h_prev
        _give_back(grads)
        return dx, dw_ih, dw_hh, *db


def gru_sequence(x: Tensor, rnn: nn.GRU) -> Tensor:
    """Return the outputs ``[T, M, H]`` of a one-layer ``rnn`` over time-major ``x [T, M, in]`` from a zero
    hidden state; differentiable."""
    if rnn.num_layers != 1 or rnn.bidirectional or not rnn.bias:
        raise ValueError("gru_sequence supports a one-layer, unidirectional GRU with biases")
    args = (x.contiguous(), rnn.weight_ih_l0, rnn.weight_hh_l0, rnn.bias_ih_l0, rnn.bias_hh_l0)
    if torch.is_grad_enabled() and any(a.requires_grad for a in args):
        return _GRUSequence.apply(*args)
    return gru_forward(*args)[1:]
