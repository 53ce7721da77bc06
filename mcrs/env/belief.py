"""Dempster-Shafer belief of a cell from its detection counts (paper eqs. 3-9 and 12).

With N+ positive and N- negative readings, f = (1 - m_f)^N+ and e = (1 - m_e)^N-:

    D = f + e - e f,   m(E) = (f - e f) / D,   m(F) = (e - e f) / D,   m(U) = e f / D.

It is evaluated in log space and rescaled by max(f, e), so it stays finite and sums to 1 even when f and e
underflow: with M = max(log f, log e), every mass shares the denominator f' + e' - f' e' e^M >= 1, where f'
= f / e^M and e' = e / e^M."""

from __future__ import annotations

import math

import torch


def belief_masses(
    positive: torch.Tensor, negative: torch.Tensor, m_f: float, m_e: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Return (m(E), m(F), m(U)) for counts of any shape; each in [0, 1], summing to 1."""
    log_f = positive.to(torch.float32) * math.log1p(-m_f)
    log_e = negative.to(torch.float32) * math.log1p(-m_e)
    top = torch.maximum(log_f, log_e)
    f_scaled = torch.exp(log_f - top)
    e_scaled = torch.exp(log_e - top)
    f = torch.exp(log_f)
    e = torch.exp(log_e)
    denominator = f_scaled + e_scaled - f_scaled * e_scaled * torch.exp(top)
    empty = f_scaled * (1.0 - e) / denominator
    full = e_scaled * (1.0 - f) / denominator
    unknown = torch.minimum(f, e) / denominator
    return empty, full, unknown
