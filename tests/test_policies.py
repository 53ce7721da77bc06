"""The heuristic policies: only allowed moves, the intended behaviour, seeding and the registry."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from mcrs.env import MOVES, SURROUNDING, MCRSEnv, scenario
from mcrs.env.layout import ObservationLayout
from mcrs.policies import POLICIES, GreedyPolicy, LawnmowerPolicy, make_policy
from mcrs.policies.lawnmower import strip_bounds

ACTION = ("agents", "action")


def _rollout(name: str, policy: str, num_envs: int, seed: int, **overrides) -> TensorDict:
    cfg = scenario(name, num_envs=num_envs, **overrides)
    env = MCRSEnv(cfg)
    env.set_seed(seed)
    with torch.no_grad():
        return env.rollout(cfg.max_steps, make_policy(policy, cfg, seed), break_when_any_done=False)


@pytest.mark.parametrize("policy", sorted(POLICIES))
@pytest.mark.parametrize("name", ["map10", "map15", "map20"])
def test_full_episodes_use_only_allowed_actions(name: str, policy: str) -> None:
    cfg = scenario(name)
    assert cfg.invalid_action == "raise"  # a masked action would abort the rollout
    td = _rollout(name, policy, num_envs=4, seed=11)
    assert td.batch_size == (4, cfg.max_steps)
    action = td.get(ACTION)
    assert action.dtype == torch.int64 and action.shape == (4, cfg.max_steps, cfg.n_uavs)
    allowed = td.get(("agents", "action_mask")).gather(-1, action.unsqueeze(-1))
    assert allowed.all()


@pytest.mark.parametrize("policy", sorted(POLICIES))
def test_every_heuristic_obeys_both_shields(policy: str) -> None:
    # The shields narrow the mask (mcrs/env/shield.py); a policy that ignored it would abort the rollout.
    td = _rollout("map20", policy, num_envs=4, seed=3, no_fly_shield=True, uav_shield=True)
    allowed = td.get(("agents", "action_mask")).gather(-1, td.get(ACTION).unsqueeze(-1))
    assert allowed.all()
    assert td.get(("next", "agents", "action_mask")).logical_not().any()  # the shields did mask moves


def test_lawnmower_under_a_mask_takes_the_allowed_move_nearest_its_waypoint() -> None:
    cfg = scenario("map10", num_envs=1)
    mask = torch.ones(1, cfg.n_uavs, 8, dtype=torch.bool)
    mask[0, 0, MOVES.index((-1, -1))] = (
        False  # UAV 0 heads for (0, 0) along the diagonal: that move is masked
    )
    action, _ = _lawnmower_first_actions(cfg, mask)
    # (8, 9) and (9, 8) are equally near (0, 0) (squared 145); the lower action of the two is taken.
    assert action[0] == min(MOVES.index((-1, 0)), MOVES.index((0, -1)))
    assert MOVES[action[1]] == (0, 1)  # unmasked UAVs keep the sign move


def test_registry_and_unknown_name() -> None:
    cfg = scenario("map10")
    assert set(POLICIES) == {"random", "lawnmower", "greedy", "coverage"}
    for name, cls in POLICIES.items():
        assert isinstance(make_policy(name, cfg, 0), cls)
    with pytest.raises(ValueError, match=r"unknown policy 'nope'.*greedy.*lawnmower.*random"):
        make_policy("nope", cfg, 0)


@pytest.mark.parametrize("policy", sorted(POLICIES))
def test_same_seed_same_actions(policy: str) -> None:
    first = _rollout("map10", policy, num_envs=3, seed=4).get(ACTION)
    again = _rollout("map10", policy, num_envs=3, seed=4).get(ACTION)
    assert torch.equal(first, again)


def test_random_policy_depends_on_seed_and_is_uniform_over_allowed() -> None:
    assert not torch.equal(
        _rollout("map10", "random", 2, seed=1).get(ACTION), _rollout("map10", "random", 2, seed=2).get(ACTION)
    )
    cfg = scenario("map10", num_envs=4000)
    policy = make_policy("random", cfg, 0)
    mask = torch.zeros(4000, cfg.n_uavs, 8, dtype=torch.bool)
    mask[..., [1, 3, 6]] = True  # the corner (0, 0): right, up, upper-right
    td = TensorDict(
        {"agents": TensorDict({"action_mask": mask}, batch_size=[4000, cfg.n_uavs])}, batch_size=[4000]
    )
    counts = torch.bincount(policy(td).get(ACTION).flatten(), minlength=8).float()
    assert counts[[0, 2, 4, 5, 7]].sum() == 0
    assert torch.allclose(counts[[1, 3, 6]] / counts.sum(), torch.full((3,), 1 / 3), atol=0.02)


# ------------------------------------------------------------------------------------------------ lawnmower
def test_lawnmower_strips_partition_the_columns() -> None:
    for name in ("map10", "map15", "map20"):
        cfg = scenario(name)
        first, width = strip_bounds(cfg)
        columns = torch.cat(
            [torch.arange(f, f + w) for f, w in zip(first.tolist(), width.tolist(), strict=True)]
        )
        assert torch.equal(columns, torch.arange(cfg.width))  # disjoint, in order, every column


def test_lawnmower_sweeps_its_whole_strip_on_map10() -> None:
    cfg = scenario("map10")
    td = _rollout("map10", "lawnmower", num_envs=8, seed=0)
    coverage = td.get(("next", "metrics", "coverage"))[:, -1]
    assert (coverage == 1.0).all()
    first, width = strip_bounds(cfg)
    position = torch.cat([td.get(("agents", "position")), td.get(("next", "agents", "position"))[:, -1:]], 1)
    x = position[..., 0]  # [E, T+1, N]
    in_strip = (x >= first) & (x < first + width)
    # Once in its strip (it starts anywhere), a UAV never leaves it.
    entered = in_strip.int().cummax(dim=1).values.bool()
    assert torch.equal(in_strip, entered)
    assert in_strip.float().mean() > 0.8
    # And it visits every cell of its strip within T = 50 steps.
    for e in range(td.batch_size[0]):
        for i in range(cfg.n_uavs):
            visited = {tuple(p) for p in position[e, :, i].tolist()}
            strip = {(sx, sy) for sx in range(first[i], first[i] + width[i]) for sy in range(cfg.height)}
            assert strip <= visited


def test_lawnmower_restarts_its_path_at_a_new_episode() -> None:
    """The pointer state is reset where step_count == 0: a reused policy acts like a fresh one."""
    cfg = scenario("map10", num_envs=3)
    used = make_policy("lawnmower", cfg, 0)
    env = MCRSEnv(cfg)
    env.set_seed(1)
    env.rollout(17, used, break_when_any_done=False)  # leaves the pointers mid-path
    env.set_seed(2)
    again = env.rollout(cfg.max_steps, used, break_when_any_done=False).get(ACTION)
    env.set_seed(2)
    fresh = env.rollout(cfg.max_steps, make_policy("lawnmower", cfg, 0), break_when_any_done=False).get(
        ACTION
    )
    assert torch.equal(again, fresh)


#: Lawnmower test positions on map10: UAV 0 (strip x in [0, 2), snake ends (0, 0) and (1, 0)) at (9, 9):
#: both ends are 9 moves away, the tie goes to the snake start (0, 0), reached along the diagonal.
LAWNMOWER_POSITIONS = torch.tensor([[9, 9], [2, 0], [5, 5], [7, 9]])


def _lawnmower_first_actions(cfg, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A fresh lawnmower's first actions ``[N]`` at LAWNMOWER_POSITIONS under ``mask``, and its waypoints."""
    policy = LawnmowerPolicy(cfg, 0)
    obs = torch.zeros(1, cfg.n_uavs, cfg.obs_dim)
    obs[0, :, ObservationLayout.from_config(cfg).position] = LAWNMOWER_POSITIONS / 9.0
    td = TensorDict(
        {
            "agents": TensorDict({"observation": obs, "action_mask": mask}, batch_size=[1, cfg.n_uavs]),
            "step_count": torch.zeros(1, 1, dtype=torch.int64),
        },
        batch_size=[1],
    )
    return policy(td).get(ACTION)[0], policy.waypoint(policy.pointer)[0]


def test_lawnmower_moves_toward_waypoint_by_sign() -> None:
    cfg = scenario("map10", num_envs=1)
    action, target = _lawnmower_first_actions(cfg, torch.ones(1, cfg.n_uavs, 8, dtype=torch.bool))
    for i in range(cfg.n_uavs):
        assert MOVES[action[i]] == tuple((target[i] - LAWNMOWER_POSITIONS[i]).sign().tolist())
    assert MOVES[action[0]] == (-1, -1)
    assert MOVES[action[1]] == (0, 1)  # (2, 0) is the start of UAV 1's strip: next waypoint (2, 1)


# ------------------------------------------------------------------------------------------------ greedy
def _greedy_td(cfg, unknown_around: torch.Tensor, position=(5, 5), uavs=(), zones=()) -> TensorDict:
    """One env, UAV 0's observation hand-built: m(U) around (SURROUNDING order) and visible neighbours."""
    layout = ObservationLayout.from_config(cfg)
    obs = torch.zeros(1, cfg.n_uavs, cfg.obs_dim)
    obs[0, 0, layout.position] = torch.tensor(position, dtype=torch.float32) / 9.0
    obs[0, 0, layout.unknown_around] = unknown_around
    r = cfg.sight_range
    for slot, (dx, dy) in uavs:
        base = layout.uavs.start + 3 * slot
        obs[0, 0, base : base + 3] = torch.tensor([(dx**2 + dy**2) ** 0.5, dx, dy]) / r
    for k, (dx, dy) in zones:
        base = layout.no_fly.start + 3 * k
        obs[0, 0, base : base + 3] = torch.tensor([(dx**2 + dy**2) ** 0.5, dx, dy]) / r
    x, y = position
    mask = torch.ones(1, cfg.n_uavs, 8, dtype=torch.bool)
    for a, (dx, dy) in enumerate(MOVES):
        mask[0, 0, a] = 0 <= x + dx < cfg.width and 0 <= y + dy < cfg.height
    return TensorDict(
        {
            "agents": TensorDict({"observation": obs, "action_mask": mask}, batch_size=[1, cfg.n_uavs]),
            "step_count": torch.ones(1, 1, dtype=torch.int64),
        },
        batch_size=[1],
    )


def test_greedy_picks_the_highest_unknown_allowed_move() -> None:
    cfg = scenario("map10")
    g = torch.Generator().manual_seed(0)
    for trial in range(20):
        values = torch.rand(8, generator=g)
        best_cell = SURROUNDING[int(values.argmax())]
        action = GreedyPolicy(cfg, trial)(_greedy_td(cfg, values)).get(ACTION)[0, 0].item()
        assert MOVES[action] == best_cell  # SURROUNDING order mapped to action order
    # At the left edge the best cell is off the grid (masked): the best allowed one wins.
    values = torch.tensor([0.9, 0.95, 0.99, 0.1, 0.2, 0.3, 0.5, 0.4])  # best three have dx = -1
    action = GreedyPolicy(cfg, 0)(_greedy_td(cfg, values, position=(0, 5))).get(ACTION)[0, 0].item()
    assert MOVES[action] == (1, 0)


def test_greedy_avoids_visible_no_fly_zone_and_uav_under_near() -> None:
    cfg = scenario("map10", safety_rule="near")
    values = torch.full((8,), 0.2)
    values[SURROUNDING.index((1, 0))] = 1.0  # right is by far the most informative...
    values[SURROUNDING.index((1, 1))] = 0.6
    td = _greedy_td(cfg, values, zones=[(1, (2, 0))])  # ...but ends next to a no-fly zone at (+2, 0)
    assert MOVES[GreedyPolicy(cfg, 0)(td).get(ACTION)[0, 0].item()] == (1, 1)  # sqrt(2) > d1 = 1
    td = _greedy_td(cfg, values, uavs=[(1, (1, 1))])  # a UAV at (+1, +1): right and upper-right too close
    action = GreedyPolicy(cfg, 0)(td).get(ACTION)[0, 0].item()
    assert MOVES[action] not in {(1, 0), (1, 1), (0, 1)}
    # Invisible entities (all-zero features) are ignored: right again.
    assert MOVES[GreedyPolicy(cfg, 0)(_greedy_td(cfg, values)).get(ACTION)[0, 0].item()] == (1, 0)


def test_greedy_avoids_only_entering_a_zone_or_a_uav_cell_under_enter() -> None:
    cfg = scenario("map10")  # the default: safety_rule=enter
    values = torch.full((8,), 0.2)
    values[SURROUNDING.index((1, 0))] = 1.0
    values[SURROUNDING.index((1, 1))] = 0.6
    td = _greedy_td(cfg, values, zones=[(1, (2, 0))])  # right ends beside the zone: not charged
    assert MOVES[GreedyPolicy(cfg, 0)(td).get(ACTION)[0, 0].item()] == (1, 0)
    td = _greedy_td(cfg, values, zones=[(1, (1, 0))])  # right ends in the zone: charged
    assert MOVES[GreedyPolicy(cfg, 0)(td).get(ACTION)[0, 0].item()] == (1, 1)
    td = _greedy_td(cfg, values, uavs=[(1, (1, 0))])  # a UAV on the right cell: only that move is charged
    assert MOVES[GreedyPolicy(cfg, 0)(td).get(ACTION)[0, 0].item()] == (1, 1)


def test_greedy_breaks_ties_randomly_but_reproducibly() -> None:
    cfg = scenario("map10")
    values = torch.full((8,), 0.5)
    values[SURROUNDING.index((0, 1))] = 0.9
    values[SURROUNDING.index((-1, -1))] = 0.9
    chosen = {
        MOVES[GreedyPolicy(cfg, s)(_greedy_td(cfg, values)).get(ACTION)[0, 0].item()] for s in range(16)
    }
    assert chosen == {(0, 1), (-1, -1)}
    first = GreedyPolicy(cfg, 3)(_greedy_td(cfg, values)).get(ACTION)
    assert torch.equal(first, GreedyPolicy(cfg, 3)(_greedy_td(cfg, values)).get(ACTION))


def test_greedy_beats_random_on_map10() -> None:
    rewards = {}
    for policy in ("random", "greedy"):
        metrics = _rollout("map10", policy, num_envs=16, seed=0).get(("next", "metrics"))[:, -1]
        rewards[policy] = metrics.get("episode_reward").mean().item()
        if policy == "greedy":
            assert metrics.get("no_fly_violations").mean() < 0.5  # it sees and avoids the zones
    assert rewards["greedy"] > rewards["random"] + 20.0
