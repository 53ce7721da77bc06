"""What the paper's delta means: the tolerance within which two standardised keys are "the same state".

The paper (section 6.3, eq. 35, after EMU) sizes delta from the buffer as ``delta = (2 * 3 sigma_x)^dim(x) / M``:
the key-space volume each of M entries would own in a full, evenly spread buffer. With sigma = 1,
dim(x) = 4 and M = 1M that is table 3's 1.3e-3. Two readings:

* ``volume`` (default): an entry matches a neighbourhood of volume delta, a box of half-side
  ``delta^(1/d) / 2`` (0.095 at d = 4) or a ball of the same volume. States merge and look-ups find other
  trajectories' memories, as section 5.2 and figure 3e describe.
* ``literal``: delta is the tolerance itself, as in EMU's code (``np.allclose(..., atol=delta)``). At
  1.3e-3 the nearest other key lies 20-65x farther, so no two states merge (docs/MEMORY.md).
"""

from __future__ import annotations

import math

from mcrs.choices import DELTA_RULES


def unit_ball_volume(dim: int) -> float:
    """Volume of the Euclidean unit ball in ``dim`` dimensions: pi^(d/2) / Gamma(d/2 + 1)."""
    return math.pi ** (dim / 2) / math.gamma(dim / 2 + 1)


def match_tolerance(delta: float, rule: str, shape: str, key_dim: int) -> float:
    """Return the tolerance the index applies for ``delta``: a box half-side or ball radius in standardised
    units. ``rule="literal"`` returns ``delta``; ``rule="volume"`` returns the tolerance whose ``shape`` in
    ``key_dim`` dimensions has volume ``delta``."""
    if rule not in DELTA_RULES:
        raise ValueError(f"delta rule must be one of {', '.join(DELTA_RULES)}, got {rule!r}")
    if not (isinstance(delta, (int, float)) and 0 < delta < math.inf):
        raise ValueError(f"delta must be a finite number > 0, got {delta!r}")
    if rule == "literal":
        return float(delta)
    if shape == "box":
        return 0.5 * delta ** (1.0 / key_dim)
    if shape == "ball":
        return (delta / unit_ball_volume(key_dim)) ** (1.0 / key_dim)
    raise ValueError(f"shape must be one of ball, box, got {shape!r}")
