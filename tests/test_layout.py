"""ObservationLayout / StateLayout against what the simulator actually produces."""

from __future__ import annotations

import itertools

import pytest
import torch

from mcrs.env import MOVES, SURROUNDING, MCRSCore, scenario
from mcrs.env.layout import ACTION_TO_SURROUNDING, ObservationLayout, StateLayout


@pytest.mark.parametrize("name", ["map10", "map15", "map20"])
def test_slices_tile_the_observation(name: str) -> None:
    cfg = scenario(name)
    layout = ObservationLayout.from_config(cfg)
    parts = [layout.position, layout.unknown_around, layout.full_around, layout.uavs, layout.no_fly]
    assert [p.stop - p.start for p in parts] == [2, 8, 8, 3 * (cfg.n_uavs - 1), 3 * cfg.n_no_fly]
    assert parts[0].start == 0 and parts[-1].stop == cfg.obs_dim == layout.obs_dim
    assert all(a.stop == b.start for a, b in itertools.pairwise(parts))
    state = StateLayout.from_config(cfg)
    spans = [state.unknown, state.full, state.uav_position, state.no_fly_position, state.target_position]
    assert spans[-1].stop == cfg.state_dim and all(a.stop == b.start for a, b in itertools.pairwise(spans))


def test_action_to_surrounding_maps_each_move_to_its_cell() -> None:
    assert sorted(ACTION_TO_SURROUNDING) == list(range(8))
    for action, index in enumerate(ACTION_TO_SURROUNDING):
        assert SURROUNDING[index] == MOVES[action]
    assert tuple(range(8)) != ACTION_TO_SURROUNDING  # the two orders really differ


def _random_walk(core: MCRSCore, steps: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    result = core.reset()
    for _ in range(steps):
        action = torch.multinomial(result.action_mask.view(-1, 8).float(), 1, generator=g)
        result = core.step(action.view(core.num_envs, core.n_uavs))
    return result


@pytest.mark.parametrize("name, steps", [("map10", 7), ("map15", 12), ("map20", 3)])
def test_layout_reads_the_core_observation(name: str, steps: int) -> None:
    cfg = scenario(name, num_envs=3, expose_beliefs=True)
    core = MCRSCore(cfg)
    core.seed(5)
    result = _random_walk(core, steps, seed=1)
    layout = ObservationLayout.from_config(cfg)
    obs, pos, beliefs = result.observation, result.position, result.belief_map  # beliefs [E, N, 2, W, H]
    assert obs.shape[-1] == layout.obs_dim
    assert torch.equal(layout.cell(obs), pos)

    unknown_by_action = layout.unknown_by_action(obs)
    full_by_action = layout.full_by_action(obs)
    uav_offset, uav_visible = layout.relative_cells(layout.uav_features(obs))
    zone_offset, zone_visible = layout.relative_cells(layout.no_fly_features(obs))
    for e in range(cfg.num_envs):
        for i in range(cfg.n_uavs):
            x, y = pos[e, i].tolist()
            for k, (dx, dy) in enumerate(SURROUNDING):
                on_grid = 0 <= x + dx < cfg.width and 0 <= y + dy < cfg.height
                expected = beliefs[e, i, :, x + dx, y + dy] if on_grid else torch.zeros(2)
                assert obs[e, i, layout.unknown_around][k] == pytest.approx(expected[0].item(), abs=1e-6)
                assert obs[e, i, layout.full_around][k] == pytest.approx(expected[1].item(), abs=1e-6)
            for a, (dx, dy) in enumerate(MOVES):
                if 0 <= x + dx < cfg.width and 0 <= y + dy < cfg.height:
                    assert unknown_by_action[e, i, a] == pytest.approx(
                        beliefs[e, i, 0, x + dx, y + dy].item()
                    )
                    assert full_by_action[e, i, a] == pytest.approx(beliefs[e, i, 1, x + dx, y + dy].item())
            others = [j for j in range(cfg.n_uavs) if j != i]
            for slot, j in enumerate(others):
                delta = pos[e, j] - pos[e, i]
                seen = 0 < delta.float().norm() <= cfg.sight_range
                assert bool(uav_visible[e, i, slot]) == bool(seen)
                if seen:
                    assert torch.equal(uav_offset[e, i, slot], delta)
            for k in range(cfg.n_no_fly):
                delta = core.no_fly_pos[e, k] - pos[e, i]
                seen = 0 < delta.float().norm() <= cfg.sight_range
                assert bool(zone_visible[e, i, k]) == bool(seen)
                if seen:
                    assert torch.equal(zone_offset[e, i, k], delta)
    # The test must have exercised visible entities, or the loops above prove little.
    assert uav_visible.any() and zone_visible.any()


def test_state_layout_decodes_positions_and_maps() -> None:
    cfg = scenario("map15", num_envs=2)
    core = MCRSCore(cfg)
    core.seed(3)
    result = _random_walk(core, 4, seed=2)
    layout = StateLayout.from_config(cfg)
    assert torch.equal(layout.cells(result.state, layout.uav_position), result.position)
    assert torch.equal(layout.cells(result.state, layout.no_fly_position), core.no_fly_pos)
    assert torch.equal(layout.cells(result.state, layout.target_position), core.target_pos)
    assert torch.equal(layout.maps(result.state), result.state_map)
    # What the codec and the CNN embedding read: the maps' image at the head, then every position.
    image = layout.map_image
    assert image.shape == (2, cfg.width, cfg.height) and image.dim == layout.map_dim == 2 * cfg.n_cells
    assert torch.equal(image.image(result.state), result.state_map)
    assert layout.positions == slice(layout.map_dim, cfg.state_dim)
    assert layout.n_positions == cfg.n_uavs + cfg.n_no_fly + cfg.n_targets
    assert torch.equal(image.rest(result.state), result.state[..., layout.positions])
    assert torch.equal(
        layout.cells(result.state, layout.positions),
        torch.cat([result.position, core.no_fly_pos, core.target_pos], dim=-2),
    )
