"""Evidence that fades (``evidence_decay``, beyond the paper): a detection of step s weighs keep^(t - s) at
step t.

Here ``keep = 1 - evidence_decay``. Ageing every UAV's map each step would cost N L1 L2 per environment, so
a UAV's counts are stored as float64 sums of keep^-s and read at step t as stored * keep^t. Fusion is
unchanged, since every copy of q's map ages alike. The global map is read whole every step, so it is kept
as float32 counts and aged in place. Config validation bounds ``max_steps * -ln(keep)`` by 80, so keep^-s
stays finite and keep^t a normal float32."""

from __future__ import annotations

import math

import torch

from mcrs.env.config import EnvConfig


class EvidenceDecay:
    """The weights of detections by step, and the factor that turns stored counts into counts now."""

    def __init__(self, config: EnvConfig, device: torch.device) -> None:
        self.keep = 1.0 - config.evidence_decay
        self.log_keep = math.log1p(-config.evidence_decay)
        steps = torch.arange(config.max_steps + 1, dtype=torch.float64, device=device)
        self.step_weight = torch.exp(-self.log_keep * steps)  # [T + 1]: keep^-s

    def factor(self, step: torch.Tensor) -> torch.Tensor:
        """``[E]`` float64: keep^t at each environment's step ``t``."""
        return torch.exp(self.log_keep * step.to(torch.float64))

    def now(self, stored: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
        """Read stored counts ``[E, ...]`` at each environment's step, as float32 counts."""
        factor = self.factor(step).view(-1, *([1] * (stored.dim() - 1)))
        return (stored * factor).to(torch.float32)
