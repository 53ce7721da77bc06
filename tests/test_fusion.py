"""Max-plus-sum fusion: the paper's example, and the fast form against the direct oracle."""

import math

import pytest
import torch

from mcrs.env import MCRSCore, scenario
from mcrs.env.belief import belief_masses
from mcrs.env.fusion import (
    DirectFusion,
    apply_new_detections,
    fuse_known,
    neighbour_graph,
    reachable_within,
)


def test_paper_example_direct_form():
    # One cell; UAVs A, B, C. A holds (A3, B1, C0), B holds (A1, B3, C1); A and B are neighbours.
    oracle = DirectFusion(n_envs=1, n_uavs=3, n_cells=1)
    oracle.maps[0, 0, :, 0, 0] = torch.tensor([3, 1, 0])
    oracle.maps[0, 1, :, 0, 0] = torch.tensor([1, 3, 1])
    neighbours = torch.tensor([[[False, True, False], [True, False, False], [False, False, False]]])
    oracle.exchange(neighbours)
    assert oracle.maps[0, 0, :, 0, 0].tolist() == [3, 3, 1]
    assert oracle.summed_counts()[0, 0, 0, 0].item() == 7  # not 5, as taking the max of sums would give
    assert oracle.summed_counts()[0, 1, 0, 0].item() == 7


def test_paper_example_fast_form():
    # Every UAV read "F" on cell 0 at steps 0, 1, 2: log entry cell * 2 + channel = 0.
    log = torch.zeros(1, 3, 3, dtype=torch.int16)
    known = torch.tensor([[[3, 1, 0], [1, 3, 1], [0, 0, 1]]])
    counts = torch.zeros(1, 3, 2, dtype=torch.int16)
    apply_new_detections(counts, torch.zeros_like(known), known, log)
    assert counts[0, :, 0].tolist() == [4, 5, 1]
    neighbours = torch.tensor([[[False, True, False], [True, False, False], [False, False, False]]])
    fused = fuse_known(known, reachable_within(neighbours, 1))
    apply_new_detections(counts, known, fused, log)
    assert fused[0, 0].tolist() == [3, 3, 1]
    assert counts[0, 0, 0].item() == 7 and counts[0, 1, 0].item() == 7 and counts[0, 2, 0].item() == 1


def test_neighbours_are_strictly_within_range_and_exclude_self():
    positions = torch.tensor([[[0, 0], [3, 4], [0, 4], [0, 0]]])  # distances 5, 4 and 0 from UAV 0
    graph = neighbour_graph(positions, 5.0)[0]
    assert graph[0].tolist() == [False, False, True, True]  # 5 is not < 5; a UAV on the same cell is
    assert not graph.diagonal().any()
    assert not neighbour_graph(positions, 0.0).any()  # comm_range 0: no communication at all
    assert neighbour_graph(positions, math.inf)[0].sum().item() == 12


@pytest.mark.parametrize("rounds", [1, 2, 3, 5, 9])
def test_reachability_equals_repeated_rounds(rounds):
    generator = torch.Generator().manual_seed(rounds)
    neighbours = torch.rand(64, 10, 10, generator=generator) < 0.15
    neighbours = (neighbours | neighbours.transpose(1, 2)) & ~torch.eye(10, dtype=torch.bool)
    known = torch.randint(0, 50, (64, 10, 10), generator=generator)
    expected = known
    for _ in range(rounds):
        expected = fuse_known(expected, reachable_within(neighbours, 1))
    assert torch.equal(fuse_known(known, reachable_within(neighbours, rounds)), expected)


def replay_with_oracle(core: MCRSCore, steps: int, rounds: int, seed: int) -> None:
    """Step ``core`` with random allowed actions, feed the same events to the oracle, compare counts."""
    cfg = core.config
    core.seed(seed)
    result = core.reset()
    oracle = DirectFusion(cfg.num_envs, cfg.n_uavs, cfg.n_cells)
    cell = result.position[..., 0] * cfg.height + result.position[..., 1]
    oracle.sense(cell, result.reading)  # reset: every UAV senses its start cell, no exchange
    generator = torch.Generator().manual_seed(seed + 1)
    for _ in range(steps):
        scores = torch.rand(result.action_mask.shape, generator=generator).masked_fill(
            ~result.action_mask, -1
        )
        result = core.step(scores.argmax(-1))
        cell = result.position[..., 0] * cfg.height + result.position[..., 1]
        oracle.sense(cell, result.reading)
        for _ in range(rounds):
            oracle.exchange(result.neighbours)
        expected = oracle.summed_counts()
        got = core.counts.view(cfg.num_envs, cfg.n_uavs, cfg.n_cells, 2).long()
        assert torch.equal(got, expected)
        # The published belief maps are the belief of exactly these counts.
        _, full, unknown = belief_masses(expected[..., 0], expected[..., 1], cfg.m_f, cfg.m_e)
        zones = core.is_no_fly.unsqueeze(1)  # known no-fly cells read m(U) = m(F) = 0 (no_fly_prior=known)
        unknown, full = unknown.masked_fill(zones, 0.0), full.masked_fill(zones, 0.0)
        published = result.belief_map.view(cfg.num_envs, cfg.n_uavs, 2, cfg.n_cells)
        assert torch.allclose(published[:, :, 0], unknown) and torch.allclose(published[:, :, 1], full)


@pytest.mark.parametrize("comm_range", [0.0, 5.0, math.inf])
@pytest.mark.parametrize("comm_rounds", [1, 2, "flood"])
def test_fast_fusion_equals_direct_max_plus_sum(comm_range, comm_rounds):
    cfg = scenario(
        "map10", num_envs=6, n_uavs=5, comm_range=comm_range, comm_rounds=comm_rounds, expose_beliefs=True
    )
    rounds = cfg.n_uavs - 1 if comm_rounds == "flood" else comm_rounds
    replay_with_oracle(MCRSCore(cfg), steps=cfg.max_steps, rounds=rounds, seed=7)


def test_fast_fusion_equals_oracle_on_map20_sizes():
    cfg = scenario("map20", num_envs=2, max_steps=40, expose_beliefs=True)
    replay_with_oracle(MCRSCore(cfg), steps=40, rounds=1, seed=3)


def test_communication_spreads_knowledge():
    """With communication a UAV knows at least as much as alone, and strictly more somewhere."""
    seen = {}
    for comm_range in (0.0, math.inf):
        cfg = scenario("map10", num_envs=8, comm_range=comm_range, expose_beliefs=True)
        core = MCRSCore(cfg)
        replay_with_oracle(core, steps=20, rounds=1, seed=11)
        seen[comm_range] = core.counts.view(8, cfg.n_uavs, -1).sum(-1)
    assert (seen[math.inf] >= seen[0.0]).all() and (seen[math.inf] > seen[0.0]).any()
    # Without communication a UAV holds exactly its own 21 readings (reset + 20 steps).
    assert (seen[0.0] == 21).all()
