"""Training a state embedding: paper eq. 31's loss and the trainer that fits an embedding on D_E's samples.

The networks in :mod:`mcrs.models.embeddings` need none of this, since the random projection is never
trained and the memory only calls an embedding."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from mcrs.models.embeddings import StateEmbedding, positive_int


def embedding_loss(
    embedding: StateEmbedding,
    state: torch.Tensor,
    time: torch.Tensor,
    returns: torch.Tensor,
    state_weight: float = 0.1,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Paper eq. 31: ``mean (H - H_hat)^2 + state_weight * mean (s - s_hat)^2``, with already scaled
    ``returns``.

    Both terms are means over their values, this project's choice; EMU's code sums both on raw H
    (docs/MEMORY.md). A sum over hundreds of belief cells would let the reconstruction outweigh the return,
    while eq. 31 with lambda_1 = 0.1 means the return to dominate so that keys carry return semantics."""
    if not embedding.trainable:
        raise TypeError(f"{type(embedding).__name__} is not trainable: it has no decoder and no loss")
    keys = embedding(state, time)
    state_hat, return_hat = embedding.reconstruct(keys, time)
    loss_return = (return_hat - returns).square().mean()
    loss_state = (state_hat - state).square().mean()
    loss = loss_return + state_weight * loss_state
    stats = {
        "loss": loss.item(),
        "loss_return": loss_return.item(),
        "loss_state": loss_state.item(),
        "loss_state_weighted": state_weight * loss_state.item(),
    }
    return loss, stats


Sampler = Callable[[int], tuple[torch.Tensor, torch.Tensor, torch.Tensor]]


class EmbeddingTrainer:
    """Train a trainable embedding on a sample of the episodic buffer (EMU: 102,400 samples, batches of 1024).

    ``fit(sample)`` draws ``samples`` entries with ``sample(samples) -> (state [n, D], time [n], returns
    [n])`` and takes ``samples // batch_size`` Adam steps on shuffled minibatches, clipping gradients to
    norm ``grad_clip`` (EMU: pymarl's 10). Returns are standardised by the sample's mean and std first:
    ours reach hundreds, which a decoder head would need thousands of steps to fit, and the affine map
    keeps their ranking. The return term still dominates, and every fit reports both weighted terms."""

    def __init__(
        self,
        embedding: StateEmbedding,
        lr: float = 5e-4,
        batch_size: int = 1024,
        samples: int = 102_400,
        state_weight: float = 0.1,
        grad_clip: float = 10.0,
    ) -> None:
        if not embedding.trainable:
            raise TypeError(f"{type(embedding).__name__} is not trainable: there is nothing to fit")
        if not lr > 0:
            raise ValueError(f"lr must be positive, got {lr!r}")
        positive_int("batch_size", batch_size)
        positive_int("samples", samples)
        if samples < batch_size:
            raise ValueError(
                f"samples ({samples}) must be at least batch_size ({batch_size}): no step otherwise"
            )
        if not state_weight >= 0:
            raise ValueError(f"state_weight must be non-negative, got {state_weight!r}")
        if not grad_clip > 0:
            raise ValueError(f"grad_clip must be positive (inf: no clipping), got {grad_clip!r}")
        self.embedding = embedding
        self.batch_size = batch_size
        self.samples = samples
        self.state_weight = state_weight
        self.grad_clip = float(grad_clip)
        self.optimizer = torch.optim.Adam(embedding.parameters(), lr=lr)

    def fit(self, sample: Sampler, generator: torch.Generator | None = None) -> dict[str, float]:
        """Draw ``samples`` entries and take ``samples // batch_size`` Adam steps; return the mean stats over
        the steps. The minibatch order is drawn from ``generator``, or the global RNG when None. The stats
        include the return standardisation used (``return_mean``, ``return_std``)."""
        device = next(self.embedding.parameters()).device
        state, time, returns = (torch.as_tensor(x).to(device, torch.float32) for x in sample(self.samples))
        n = state.shape[0]
        if n < self.batch_size or time.shape != (n,) or returns.shape != (n,):
            raise ValueError(
                f"sample({self.samples}) must return state [n, D], time [n], returns [n] with n >= batch_size "
                f"({self.batch_size}); got {tuple(state.shape)}, {tuple(time.shape)}, {tuple(returns.shape)}"
            )
        mean, std = returns.mean(), returns.std(unbiased=False).clamp_min(1e-6)
        returns = (returns - mean) / std
        steps = n // self.batch_size
        order = torch.randperm(n, generator=generator).to(device)
        totals = {"loss": 0.0, "loss_return": 0.0, "loss_state": 0.0, "loss_state_weighted": 0.0}
        self.embedding.train()
        for step in range(steps):
            idx = order[step * self.batch_size : (step + 1) * self.batch_size]
            loss, stats = embedding_loss(
                self.embedding, state[idx], time[idx], returns[idx], state_weight=self.state_weight
            )
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(self.embedding.parameters(), self.grad_clip)
            self.optimizer.step()
            for key in totals:
                totals[key] += stats[key]
        result = {key: value / steps for key, value in totals.items()}
        result.update(steps=float(steps), return_mean=mean.item(), return_std=std.item())
        return result

    def state_dict(self) -> dict[str, Any]:
        """Return the optimizer's state for checkpoints; the embedding saves its own."""
        return {"optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.optimizer.load_state_dict(state["optimizer"])
