"""The paper's reading of no-fly cells (sections 3.1 and 4.2, figure 4), pinned on hand-set scenes.

At the defaults a UAV's surround shows 0 in a no-fly direction (``no_fly_view=blocked``) and every belief map
holds a no-fly cell as known and empty from reset (``no_fly_prior=known``); the old reading, by name, shows
the zone's belief and starts it unread. Each field alone stays selectable.
"""

from __future__ import annotations

import pytest
import torch

from mcrs.env import MCRSCore, scenario
from mcrs.env.layout import ObservationLayout

EXACT_SENSOR = {"p_detect": 1.0, "p_false_alarm": 0.0}
OLD = {"no_fly_view": "belief", "no_fly_prior": "unknown"}
READINGS = {
    "paper": {},
    "old": OLD,
    "view_alone": {"no_fly_prior": "unknown"},
    "prior_alone": {"no_fly_view": "belief"},
}
# UAV 0 at (4, 5) beside the zone (5, 5); UAV 1 far away; one target.
SCENE = ([[4, 5], [0, 0]], [[5, 5]], [[9, 9]])
EAST = 6  # (1, 0) in the surround's order D_s (mcrs/env/core.py, SURROUNDING)


def scene(reading: str, **overrides):
    cfg = scenario(
        "map10", n_uavs=2, n_no_fly=1, n_targets=1, comm_range=0.0, expose_beliefs=True,
        **{**EXACT_SENSOR, **READINGS[reading], **overrides},
    )  # fmt: skip
    core = MCRSCore(cfg)
    uavs, zones, targets = (torch.tensor(cells) for cells in SCENE)
    return core, core.reset_to(uavs, zones, targets)


@pytest.mark.parametrize("reading", sorted(READINGS))
def test_a_uav_beside_a_zone_sees_zero_there_unless_the_old_reading(reading):
    core, result = scene(reading)
    layout = ObservationLayout.from_config(core.config)
    obs = result.observation[0, 0]
    unknown, full = obs[layout.unknown_around], obs[layout.full_around]
    if reading == "old":  # the zone's own belief: unread, m(U) = 1, the most attractive cell
        assert unknown[EAST].item() == 1.0 and full[EAST].item() == 0.0
    else:  # blocked, or known and empty: both read 0
        assert unknown[EAST].item() == 0.0 and full[EAST].item() == 0.0
    # The other unread neighbours of (4, 5) show m(U) = 1 in every reading.
    others = [k for k in range(8) if k != EAST]
    assert unknown[others].tolist() == [1.0] * 7


def test_off_grid_directions_read_zero_in_every_reading():
    for reading in READINGS:
        core, result = scene(reading)
        layout = ObservationLayout.from_config(core.config)
        corner = result.observation[0, 1]  # UAV 1 at (0, 0): five directions off the grid
        unknown = corner[layout.unknown_around]
        assert unknown.tolist() == [0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 1.0, 1.0], reading


@pytest.mark.parametrize("reading", sorted(READINGS))
def test_a_zone_is_known_in_every_map_and_the_state_from_reset(reading):
    core, result = scene(reading)
    known = core.config.no_fly_prior == "known"
    zone = 5 * 10 + 5
    maps = result.belief_map.view(1, 2, 2, -1)  # [E, N, (m(U), m(F)), cells]
    expected = 0.0 if known else 1.0
    assert maps[0, :, 0, zone].tolist() == [expected, expected]  # every UAV's own map
    assert maps[0, :, 1, zone].tolist() == [0.0, 0.0]
    assert result.state[0, zone].item() == expected  # the global m(U) of the state
    # The uncertainty metric: 100 cells, 2 start cells read once (0.2 each), the zone 0 when known.
    assert result.metrics["uncertainty"].item() == pytest.approx((97 if known else 98) + 0.4)


@pytest.mark.parametrize("reading", sorted(READINGS))
def test_entering_a_zone_pays_w3_and_r1_only_when_the_zone_was_unread(reading):
    core, _ = scene(reading, w_no_fly=1.5)
    result = core.step(torch.tensor([[1, 1]]))  # UAV 0 -> (5, 5), the zone; UAV 1 -> (1, 0)
    r1, r2, r3, r4 = result.reward_terms[0].tolist()
    assert r3 == -1.5 and r4 == 0.0 and r2 == 0.0
    zone_r1 = 0.0 if core.config.no_fly_prior == "known" else 0.8  # one E reading: m(U) 1 -> 0.2
    assert r1 == pytest.approx(0.8 + zone_r1)  # UAV 1's new cell (1, 0) always pays 0.8
    assert result.state[0, 55].item() == (0.0 if zone_r1 == 0 else pytest.approx(0.2))
    assert result.metrics["no_fly_violations"].item() == 1.0


def test_a_known_zone_never_becomes_a_discovery_even_read_as_f():
    """A sensor that always reads F: the zone cell, entered twice, reaches no m(F) (known empty)."""
    core, _ = scene("paper", p_false_alarm=1.0)
    r2 = []
    for move in ([1, 3], [0, 2], [1, 3]):  # into the zone, out, in again; UAV 1 up and down
        r2.append(core.step(torch.tensor([move])).reward_terms[0, 1].item())
    assert core.global_belief[0, 1, 55].item() == 0.0
    assert not core.discovered[0, 55]
    # The empty cells read F twice are discoveries (eq. 24): UAV 0's start (4, 5) and UAV 1's (0, 0) at
    # step 2, UAV 1's (0, 1) at step 3; the zone, read F twice, is not.
    assert r2 == [0.0, 2.0, 1.0]


def test_the_far_view_counts_a_known_zone_as_read():
    values = {}
    for reading in ("paper", "old"):
        core, result = scene(reading, far_view=1)
        layout = ObservationLayout.from_config(core.config)
        values[reading] = result.observation[0, 0, layout.far_view]
    # Action 1 (right) from (4, 5): the window centred on (6, 5) holds the zone (5, 5): 1 of 9 cells is 0.
    assert values["old"][1].item() == pytest.approx(1.0)
    assert values["paper"][1].item() == pytest.approx(8 / 9)


def test_nearest_first_sorts_each_group_by_distance_and_puts_unseen_last():
    # UAV 0 at (0, 0); UAV 1 at (3, 0) (distance 3), UAV 2 at (1, 1) (sqrt 2), UAV 3 at (9, 9) (beyond sight).
    # Zones (0, 4) (distance 4), (2, 0) (2), (8, 8) (beyond sight).
    uavs = torch.tensor([[0, 0], [3, 0], [1, 1], [9, 9]])
    zones, targets = torch.tensor([[0, 4], [2, 0], [8, 8]]), torch.tensor([[5, 5]])
    rows = {}
    for order in ("index", "nearest"):
        cfg = scenario("map10", n_targets=1, relative_order=order, **EXACT_SENSOR)
        core = MCRSCore(cfg)
        result = core.reset_to(uavs, zones, targets)
        layout = ObservationLayout.from_config(cfg)
        obs = result.observation[0, 0]
        rows[order] = (obs[layout.uavs].view(-1, 3), obs[layout.no_fly].view(-1, 3))
    (uav_index, zone_index), (uav_near, zone_near) = rows["index"], rows["nearest"]
    r = 4.0  # sight range: (d, dx, dy) / R_sight
    expected = torch.tensor([[3 / r, 3 / r, 0.0], [2**0.5 / r, 1 / r, 1 / r], [0.0, 0.0, 0.0]])
    assert torch.allclose(uav_index, expected)
    assert torch.equal(uav_near, uav_index[[1, 0, 2]])  # sqrt 2, then 3, then the unseen UAV
    assert zone_index.tolist() == [[4 / r, 0.0, 4 / r], [2 / r, 2 / r, 0.0], [0.0, 0.0, 0.0]]
    assert torch.equal(zone_near, zone_index[[1, 0, 2]])


def test_the_coverage_heuristic_refuses_nearest_first_slots():
    from mcrs.policies.coverage import CoveragePolicy

    with pytest.raises(ValueError, match="relative_order=nearest is not supported"):
        CoveragePolicy(scenario("map10", relative_order="nearest"))
