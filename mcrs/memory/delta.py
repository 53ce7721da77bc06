"""What the paper's delta means: the tolerance within which two standardised keys are "the same state".

The paper (section 6.3, eq. 35, after EMU) sizes delta from the buffer: ``delta = (2 * 3 sigma_x)^dim(x) / M``,
the volume of key space (keys spread over +-3 sigma in each of dim(x) dimensions) that each of the M entries
would own if the buffer were full and evenly spread. With sigma = 1 (standardised keys), dim(x) = 4 and
M = 1M that is 1.3e-3, table 3's value. Two readings of that number:

* ``volume`` (the default): delta is that volume per entry. An entry matches the keys of a neighbourhood of
  volume delta around it: a box of half-side ``delta^(1/d) / 2`` (0.095 at 1.3e-3, d = 4) or a ball of the
  same volume. States then merge, and look-ups find the memories of other trajectories, as section 5.2
  and figure 3e describe ("retrieve memories from similar states within a larger threshold").
* ``literal``: delta is itself the tolerance (EMU's code: ``np.allclose(..., atol=delta)`` on standardised
  keys). At 1.3e-3 the nearest other key of our runs lies 20-65x farther, so no two states ever merge and
  every look-up returns a trajectory's own return (docs/MEMORY.md has the measurements).
"""

from __future__ import annotations

import math

from mcrs.choices import DELTA_RULES


def unit_ball_volume(dim: int) -> float:
    """Volume of the Euclidean unit ball in ``dim`` dimensions: pi^(d/2) / Gamma(d/2 + 1)."""
    return math.pi ** (dim / 2) / math.gamma(dim / 2 + 1)


def match_tolerance(delta: float, rule: str, shape: str, key_dim: int) -> float:
    """The tolerance the index applies (box half-side or ball radius, standardised units) for ``delta``.

    ``rule="literal"``: ``delta`` itself. ``rule="volume"``: the tolerance whose neighbourhood of ``shape``
    ("box" or "ball") in ``key_dim`` dimensions has volume ``delta``.
    """
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
