"""The no-fly shield (env option ``no_fly_shield``): which moves it masks, its fallback, and that it is off by default."""

import pytest
import torch

from mcrs.env import MCRSCore, scenario
from mcrs.env.core import MOVES

EXACT_SENSOR = {"p_detect": 1.0, "p_false_alarm": 0.0}


def scene(uavs, no_fly, shield: bool = True, **overrides) -> tuple[MCRSCore, object]:
    cfg = scenario(
        "map10",
        n_uavs=len(uavs),
        n_no_fly=len(no_fly),
        n_targets=1,
        no_fly_shield=shield,
        **{**EXACT_SENSOR, **overrides},
    )
    core = MCRSCore(cfg)
    return core, core.reset_to(torch.tensor(uavs), torch.tensor(no_fly).view(-1, 2), torch.tensor([[9, 0]]))


def allowed(result, uav: int, env: int = 0) -> set[int]:
    return set(result.action_mask[env, uav].nonzero().squeeze(-1).tolist())


def expected_mask(
    position, zones, width: int, height: int, d1: float, rule: str = "near"
) -> tuple[set[int], set[int]]:
    """(on-grid moves, on-grid moves that r3 does not charge: ending at d1 or farther from every zone under
    ``enter``, farther than d1 under ``near``), by brute force."""

    def charged(squared: int) -> bool:
        return squared < d1**2 if rule == "enter" else squared <= d1**2

    x, y = position
    on_grid = {a for a, (dx, dy) in enumerate(MOVES) if 0 <= x + dx < width and 0 <= y + dy < height}
    safe = {
        a
        for a in on_grid
        if not any(charged((x + MOVES[a][0] - zx) ** 2 + (y + MOVES[a][1] - zy) ** 2) for zx, zy in zones)
    }
    return on_grid, safe


def test_shield_masks_only_the_move_into_the_zone_under_enter():
    # Zone (5, 5), d1 = 1, the default rule: only entering the zone is charged, so only that move is masked.
    _, result = scene([[5, 3], [4, 6], [0, 0]], [[5, 5]])
    assert allowed(result, 0) == set(range(8))  # (5, 4) is beside the zone: allowed under enter
    assert allowed(result, 1) == set(range(8)) - {5}  # only the diagonal into the zone (5, 5)


def test_shield_masks_exactly_the_moves_into_d1_of_a_zone_under_near():
    # Zone (5, 5), d1 = 1: the zone cell and its 4 edge neighbours are unsafe; diagonals (sqrt 2) are safe.
    core, result = scene([[5, 3], [4, 6], [0, 0]], [[5, 5]], safety_rule="near")
    assert allowed(result, 0) == set(range(8)) - {3}  # up to (5, 4)
    assert allowed(result, 1) == set(range(8)) - {1, 2, 5}  # (5, 6), (4, 5), the zone (5, 5)
    assert allowed(result, 2) == {1, 3, 6}  # far away: the grid mask only
    # After a step the mask follows the new positions: (5, 3) -> (4, 4) is next to (4, 5) and (5, 4).
    result = core.step(torch.tensor([[7, 0, 1]]))
    assert allowed(result, 0) == set(range(8)) - {1, 3, 6}
    # Without the shield the same scene keeps every on-grid move.
    _, unshielded = scene([[5, 3], [4, 6], [0, 0]], [[5, 5]], shield=False, safety_rule="near")
    assert allowed(unshielded, 0) == set(range(8)) and allowed(unshielded, 1) == set(range(8))


def random_allowed(mask: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """One uniformly random allowed action per UAV."""
    return torch.rand(mask.shape, generator=generator).masked_fill(~mask, -1).argmax(-1)


@pytest.mark.parametrize("rule", ["enter", "near"])
@pytest.mark.parametrize("d1", [0.0, 1.0, 1.5, 2.0])
def test_shield_matches_brute_force_on_random_scenes(d1, rule):
    cfg = scenario("map10", num_envs=16, no_fly_safety=d1, no_fly_shield=True, safety_rule=rule)
    core = MCRSCore(cfg)
    core.seed(3)
    result = core.reset()
    generator = torch.Generator().manual_seed(0)
    for _ in range(5):
        for env in range(cfg.num_envs):
            zones = core.no_fly_pos[env].tolist()
            for uav in range(cfg.n_uavs):
                on_grid, safe = expected_mask(core.uav_pos[env, uav].tolist(), zones, 10, 10, d1, rule)
                assert allowed(result, uav, env) == (safe or on_grid)
        result = core.step(random_allowed(result.action_mask, generator))


def test_uav_with_no_safe_move_keeps_its_unshielded_mask():
    # Corner (0, 0) next to the zone (1, 1) with d1 = 1: (1, 0), (0, 1) and (1, 1) are all within d1.
    _, result = scene([[0, 0], [0, 5]], [[1, 1]], safety_rule="near")
    assert allowed(result, 0) == {1, 3, 6}  # fallback: the grid mask
    assert allowed(result, 1) == {1, 2, 3, 5, 6}  # the other UAV is unaffected
    # A larger d1 can leave a UAV in the open with no safe move either.
    _, result = scene([[5, 5], [0, 9]], [[5, 7]], no_fly_safety=3.5, safety_rule="near")
    assert allowed(result, 0) == set(range(8))


def test_shield_is_off_by_default_and_changes_nothing_but_the_mask():
    assert scenario("map10").no_fly_shield is False
    shielded = MCRSCore(scenario("map10", num_envs=8, no_fly_shield=True))
    plain = MCRSCore(scenario("map10", num_envs=8))
    shielded.seed(1)
    plain.seed(1)
    a, b = shielded.reset(), plain.reset()
    generator = torch.Generator().manual_seed(1)
    for _ in range(50):
        assert (a.action_mask <= b.action_mask).all()  # the shield only removes moves
        for field in ("observation", "state", "reward_terms", "position"):
            assert torch.equal(getattr(a, field), getattr(b, field)), field
        action = random_allowed(a.action_mask, generator)
        a, b = shielded.step(action), plain.step(action)


@pytest.mark.parametrize("d1", [1.0, 2.0])
def test_random_allowed_episodes_violate_only_where_the_fallback_applies(d1):
    cfg = scenario("map10", num_envs=64, no_fly_safety=d1, no_fly_shield=True, safety_rule="near")
    core = MCRSCore(cfg)
    core.seed(7)
    result = core.reset()
    generator = torch.Generator().manual_seed(7)
    fallbacks = 0
    for _ in range(cfg.max_steps):
        # Fallback UAVs: every on-grid move ends within d1 of a zone (computed here, independently).
        fallback = torch.zeros(cfg.num_envs, cfg.n_uavs, dtype=torch.bool)
        for env in range(cfg.num_envs):
            zones = core.no_fly_pos[env].tolist()
            for uav in range(cfg.n_uavs):
                _, safe = expected_mask(core.uav_pos[env, uav].tolist(), zones, 10, 10, d1)
                fallback[env, uav] = not safe
        result = core.step(random_allowed(result.action_mask, generator))
        # A violation: a (UAV, zone) pair within d1 after the move (reward term r3).
        offset = core.uav_pos.unsqueeze(2) - core.no_fly_pos.unsqueeze(1)
        pairs = (offset.pow(2).sum(-1) <= d1**2).sum(-1)  # [E, N]
        assert (pairs[~fallback] == 0).all()
        assert torch.equal(-result.reward_terms[:, 2], (pairs * fallback).sum(-1).to(torch.float32))
        fallbacks += int(fallback.sum())
    if d1 == 2.0:
        assert fallbacks > 0  # d1 = 2 exercises the fallback


def test_bad_shield_value_is_refused_naming_the_field():
    with pytest.raises(ValueError, match="no_fly_shield='yes': must be true or false"):
        scenario("map10", no_fly_shield="yes")


def test_masked_unsafe_action_is_refused_naming_the_shield():
    core, _ = scene([[5, 3], [0, 0]], [[5, 5]], safety_rule="near")  # (5, 4), beside the zone: charged
    with pytest.raises(ValueError, match=r"is masked: .*no_fly_shield"):
        core.step(torch.tensor([[3, 1]]))
