"""One optimiser step with the numerical guard shared by every learner (TD, curiosity, embedding)."""

from __future__ import annotations

import torch
from torch import nn


class TrainingDiverged(RuntimeError):
    """A loss or gradient became NaN or infinite."""


def gradient_step(
    loss: torch.Tensor,
    optimizer: torch.optim.Optimizer,
    params: list[nn.Parameter],
    grad_clip: float,
    step: int,
    term: str = "loss_td",
) -> torch.Tensor:
    """Backward, clip and step; return the gradient norm. Raises :class:`TrainingDiverged` before the weights
    change when the loss or the gradient norm is not finite; ``step`` and ``term`` name where."""
    if not torch.isfinite(loss):
        raise TrainingDiverged(f"non-finite {term}={loss.item()} at env step {step}")
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    grad_norm = nn.utils.clip_grad_norm_(params, grad_clip)
    if not torch.isfinite(grad_norm):
        raise TrainingDiverged(f"non-finite gradient norm of {term}={grad_norm.item()} at env step {step}")
    optimizer.step()
    return grad_norm
