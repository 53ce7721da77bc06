"""The safety shields (env options ``no_fly_shield`` and ``uav_shield``): which moves they mask, their fallback,
and that they are off by default."""

import math

import pytest
import torch

from mcrs.env import MCRSCore, scenario
from mcrs.env.core import MOVES
from tests.device_helpers import available_devices

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


@pytest.mark.parametrize(("option", "seed"), [("no_fly_shield", 1), ("uav_shield", 2)])
def test_each_shield_is_off_by_default_and_changes_nothing_but_the_mask(option: str, seed: int):
    assert getattr(scenario("map10"), option) is False
    shielded = MCRSCore(scenario("map10", num_envs=8, **{option: True}))
    plain = MCRSCore(scenario("map10", num_envs=8))
    shielded.seed(seed)
    plain.seed(seed)
    a, b = shielded.reset(), plain.reset()
    generator = torch.Generator().manual_seed(seed)
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


# ----------------------------------------------------------------------------- the right of way (r4)
def on_grid_moves(position, width: int, height: int) -> set[int]:
    x, y = position
    return {a for a, (dx, dy) in enumerate(MOVES) if 0 <= x + dx < width and 0 <= y + dy < height}


def unsafe_moves(
    positions, own: set[int], index: int, d2: float, sight: float, size: int, rule: str = "enter"
) -> set[int]:
    """Of UAV ``index``'s moves ``own``, those that end where r4 charges with some on-grid move of a
    lower-indexed UAV within ``sight`` (on a ``size`` x ``size`` grid), by brute force."""

    def charged(squared: int) -> bool:
        return squared < d2**2 if rule == "enter" else squared <= d2**2

    x, y = positions[index]
    unsafe = set()
    for j in range(index):
        jx, jy = positions[j]
        if (jx - x) ** 2 + (jy - y) ** 2 > sight**2:
            continue
        for a in own:
            ax, ay = x + MOVES[a][0], y + MOVES[a][1]
            for b in on_grid_moves((jx, jy), size, size):
                if charged((ax - jx - MOVES[b][0]) ** 2 + (ay - jy - MOVES[b][1]) ** 2):
                    unsafe.add(a)
    return unsafe


def expected_right_of_way(
    positions, own: set[int], index: int, d2: float, sight: float, size: int, rule: str = "enter"
) -> set[int]:
    """UAV ``index``'s moves under ``uav_shield``: its moves ``own`` less the unsafe ones, or all of them
    if that leaves none."""
    return (own - unsafe_moves(positions, own, index, d2, sight, size, rule)) or own


def test_right_of_way_masks_the_cells_a_lower_indexed_uav_in_sight_may_reach():
    # UAV 0 at (5, 5), UAV 1 at (5, 7): UAV 0 might move to any cell of row y = 6 around it, so UAV 1 may
    # not; UAV 2 far away is unaffected; UAV 0 never gives way.
    def reset(**overrides):
        cfg = scenario(
            "map10", n_uavs=3, n_no_fly=1, n_targets=1, uav_shield=True, **EXACT_SENSOR, **overrides
        )
        uavs, zone, target = (
            torch.tensor([[5, 5], [5, 7], [0, 0]]),
            torch.tensor([[9, 9]]),
            torch.tensor([[9, 0]]),
        )
        return MCRSCore(cfg).reset_to(uavs, zone, target)

    result = reset()
    row_6 = {a for a, (dx, dy) in enumerate(MOVES) if dy == -1}
    assert len(row_6) == 3
    assert allowed(result, 0) == set(range(8))
    assert allowed(result, 1) == set(range(8)) - row_6
    assert allowed(result, 2) == {1, 3, 6}  # the grid mask only
    # Out of sight (sight_range 1.5 < 2), UAV 1 does not see UAV 0 and keeps every move.
    assert allowed(reset(sight_range=1.5), 1) == set(range(8))
    # Under near with d2 = 1, side by side is charged too: UAV 1 may not end next to any cell UAV 0 may reach.
    near = reset(safety_rule="near")
    assert allowed(near, 1) == {a for a, (dx, dy) in enumerate(MOVES) if dy == 1}


@pytest.mark.parametrize("rule", ["enter", "near"])
@pytest.mark.parametrize("d2", [0.0, 1.0, 2.0, 5.5, math.inf])
def test_right_of_way_matches_brute_force_on_random_scenes(d2, rule):
    options = {"num_envs": 16, "uav_safety": d2, "safety_rule": rule, "no_fly_shield": True}
    shielded = MCRSCore(scenario("map10", uav_shield=True, **options))
    plain = MCRSCore(scenario("map10", **options))
    shielded.seed(5)
    plain.seed(5)
    a, b = shielded.reset(), plain.reset()
    cfg = shielded.config
    generator = torch.Generator().manual_seed(5)
    for _ in range(6):
        assert torch.equal(shielded.uav_pos, plain.uav_pos)
        for env in range(cfg.num_envs):
            positions = shielded.uav_pos[env].tolist()
            for uav in range(cfg.n_uavs):
                own = allowed(b, uav, env)  # the no-fly shield's mask, before the right of way
                want = expected_right_of_way(positions, own, uav, d2, cfg.sight_range, cfg.width, rule)
                assert allowed(a, uav, env) == want
        action = random_allowed(a.action_mask, generator)
        a, b = shielded.step(action), plain.step(action)


def test_random_allowed_episodes_collide_only_where_the_right_of_way_fell_back():
    cfg = scenario("map20", num_envs=32, uav_shield=True)
    core = MCRSCore(cfg)
    core.seed(11)
    result = core.reset()
    generator = torch.Generator().manual_seed(11)
    avoided = 0
    for _ in range(cfg.max_steps):
        # An env where some UAV had every move unsafe (the shield then keeps them all), computed here.
        fell_back = torch.zeros(cfg.num_envs, dtype=torch.bool)
        for env in range(cfg.num_envs):
            positions = core.uav_pos[env].tolist()
            for uav in range(cfg.n_uavs):
                own = on_grid_moves(positions[uav], cfg.width, cfg.height)
                unsafe = unsafe_moves(positions, own, uav, cfg.uav_safety, cfg.sight_range, cfg.width)
                fell_back[env] |= own <= unsafe
                avoided += len(unsafe) > 0
        result = core.step(random_allowed(result.action_mask, generator))
        assert (result.reward_terms[~fell_back, 3] == 0).all()
    assert avoided > 100  # the UAVs met often enough for the shield to matter
    unshielded = MCRSCore(scenario("map20", num_envs=32))
    unshielded.seed(11)
    result = unshielded.reset()
    for _ in range(cfg.max_steps):
        result = unshielded.step(random_allowed(result.action_mask, generator))
    assert unshielded.collisions.sum() > 100  # the same play without it collides


def test_bad_right_of_way_value_is_refused_naming_the_field():
    with pytest.raises(ValueError, match="uav_shield=1: must be true or false"):
        scenario("map10", uav_shield=1)


def test_masked_move_towards_a_uav_is_refused_naming_the_right_of_way():
    core = MCRSCore(scenario("map10", n_uavs=2, n_no_fly=1, n_targets=1, uav_shield=True, **EXACT_SENSOR))
    core.reset_to(torch.tensor([[5, 5], [5, 7]]), torch.tensor([[9, 9]]), torch.tensor([[9, 0]]))
    towards = next(a for a, (dx, dy) in enumerate(MOVES) if (dx, dy) == (0, -1))
    with pytest.raises(ValueError, match=r"is masked: .*uav_shield"):
        core.step(torch.tensor([[0, towards]]))


@pytest.mark.parametrize("device", available_devices())
def test_both_shields_mask_and_charge_the_same_on_every_device(device: str):
    """Both shields on the device (CUDA where a GPU is lent): the same masks and rewards as on the CPU for
    the same scene and moves, and no no-fly charge (a UAV here always has a safe move)."""
    uavs, zones = [[4, 4], [5, 4], [4, 5], [6, 6]], [[5, 5], [3, 3]]

    def play(where: str) -> tuple[torch.Tensor, torch.Tensor]:
        cfg = scenario(
            "map10",
            num_envs=16,
            n_uavs=4,
            n_no_fly=2,
            n_targets=1,
            no_fly_shield=True,
            uav_shield=True,
            device=where,
            **EXACT_SENSOR,
        )
        core = MCRSCore(cfg)
        result = core.reset_to(torch.tensor(uavs), torch.tensor(zones), torch.tensor([[9, 0]]))
        generator = torch.Generator().manual_seed(3)
        masks, terms = [], []
        for _ in range(cfg.max_steps):
            masks.append(result.action_mask.cpu())
            result = core.step(random_allowed(result.action_mask.cpu(), generator).to(where))
            terms.append(result.reward_terms.cpu())
        assert result.action_mask.device.type == torch.device(where).type
        return torch.stack(masks), torch.stack(terms)

    masks, terms = play(device)
    cpu_masks, cpu_terms = play("cpu")
    assert torch.equal(masks, cpu_masks) and torch.allclose(terms, cpu_terms)
    assert (terms[..., 2] == 0).all()  # r3: no zone entry
    assert (~masks).any()  # the shields did mask moves
