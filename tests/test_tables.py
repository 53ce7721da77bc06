"""Table cells (mcrs.experiment.util.tables)."""

from __future__ import annotations

import math

from mcrs.experiment.util.tables import mean_std


def test_mean_std_drops_the_spread_of_one_sample_and_names_a_missing_value() -> None:
    assert mean_std(1.234, 0.5) == "1.23 ± 0.50"
    assert mean_std(1.234, 0.0, n=1) == "1.23"  # one seed has no spread
    assert mean_std(math.nan, math.nan) == "n/a"  # a metric not logged
    assert mean_std(math.nan, math.nan, n=1, missing="-") == "-"  # a step not reached yet
