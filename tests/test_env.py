"""The batched environment: layouts, rewards, masks, resets, determinism, specs and bad input."""

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from mcrs.env import MCRSCore, MCRSEnv, scenario
from tests.device_helpers import available_devices

TABLE_2 = {  # map: (N, state dim, obs dim)
    "map10": (4, 226, 36),
    "map15": (8, 502, 57),
    "map20": (10, 880, 75),
}
# A sensor that never errs, so that hand-built scenes are deterministic.
EXACT_SENSOR = {"p_detect": 1.0, "p_false_alarm": 0.0}


def random_allowed(mask: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    scores = torch.rand(mask.shape, generator=generator).masked_fill(~mask, -1.0)
    return scores.argmax(-1)


def scene_core(uavs, no_fly, targets, **overrides) -> tuple[MCRSCore, object]:
    cfg = scenario(
        "map10",
        n_uavs=len(uavs),
        n_no_fly=len(no_fly),
        n_targets=len(targets),
        **{**EXACT_SENSOR, **overrides},
    )
    core = MCRSCore(cfg)
    result = core.reset_to(
        torch.tensor(uavs), torch.tensor(no_fly).view(-1, 2), torch.tensor(targets).view(-1, 2)
    )
    return core, result


@pytest.mark.parametrize("name", list(TABLE_2))
def test_table_2_dimensions(name):
    n_uavs, state_dim, obs_dim = TABLE_2[name]
    env = MCRSEnv(name, num_envs=3)
    td = env.reset()
    assert env.config.state_dim == state_dim and env.config.obs_dim == obs_dim
    assert td["agents", "observation"].shape == (3, n_uavs, obs_dim)
    assert td["state"].shape == (3, state_dim)
    assert td["state_map"].shape == (3, 2, env.config.width, env.config.height)
    assert td["agents", "action_mask"].shape == (3, n_uavs, 8)
    assert env.full_action_spec["agents", "action"].space.n == 8


@pytest.mark.parametrize("name", list(TABLE_2))
@pytest.mark.parametrize("expose_beliefs", [False, True])
def test_check_env_specs(name, expose_beliefs):
    env = MCRSEnv(name, num_envs=4, expose_beliefs=expose_beliefs)
    env.set_seed(0)
    check_env_specs(env)


def test_observation_layout_on_hand_built_scene():
    uavs = [[0, 0], [3, 4], [2, 2], [9, 9]]
    no_fly = [[0, 3], [5, 5], [9, 0]]
    targets = [[0, 0], [7, 7]]
    core, result = scene_core(uavs, no_fly, targets)
    obs = result.observation[0]
    sight = core.config.sight_range
    # UAV 0 at the corner (0, 0): position, then m(U) / m(F) of the 8 cells in D_s order.
    assert obs[0, :2].tolist() == [0.0, 0.0]
    on_grid = [False, False, False, False, True, False, True, True]  # (0,1), (1,0), (1,1)
    assert obs[0, 2:10].tolist() == [1.0 if ok else 0.0 for ok in on_grid]
    assert obs[0, 10:18].tolist() == [0.0] * 8
    # Other UAVs in index order (1, 2, 3): UAV 1 at distance 5 > R_sight is zeros; UAV 2 at (2, 2) is seen.
    assert obs[0, 18:21].tolist() == [0.0, 0.0, 0.0]
    assert torch.allclose(obs[0, 21:24], torch.tensor([math.sqrt(8), 2.0, 2.0]) / sight)
    assert obs[0, 24:27].tolist() == [0.0, 0.0, 0.0]
    # No-fly zones: (0, 3) at distance 3 is seen, the others are not.
    assert torch.allclose(obs[0, 27:30], torch.tensor([3.0, 0.0, 3.0]) / sight)
    assert obs[0, 30:36].tolist() == [0.0] * 6
    # From UAV 2 the relative offset of UAV 0 points the other way; it is the first of its others.
    assert torch.allclose(obs[2, 18:21], torch.tensor([math.sqrt(8), -2.0, -2.0]) / sight)
    assert torch.allclose(obs[3, :2], torch.tensor([1.0, 1.0]))

    # UAV 0 read its target at (0, 0) at reset. Moving up to (0, 1), the cell below it, offset (0, -1),
    # fourth in D_s, now shows m(F) = 0.8 and m(U) = 0.2 in its own fused map.
    result = core.step(torch.tensor([[3, 1, 6, 4]]))
    obs = result.observation[0]
    assert torch.isclose(obs[0, 2 + 3], torch.tensor(0.2)) and torch.isclose(
        obs[0, 10 + 3], torch.tensor(0.8)
    )


def test_surrounding_beliefs_match_the_published_belief_map():
    cfg = scenario("map15", num_envs=4, expose_beliefs=True)
    core = MCRSCore(cfg)
    generator = torch.Generator().manual_seed(0)
    result = core.reset()
    for _ in range(20):
        result = core.step(random_allowed(result.action_mask, generator))
    offsets = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]
    for env in range(4):
        for uav in range(cfg.n_uavs):
            x, y = result.position[env, uav].tolist()
            for k, (dx, dy) in enumerate(offsets):
                on_grid = 0 <= x + dx < cfg.width and 0 <= y + dy < cfg.height
                for channel, start in ((0, 2), (1, 10)):
                    expected = result.belief_map[env, uav, channel, x + dx, y + dy].item() if on_grid else 0.0
                    assert result.observation[env, uav, start + k].item() == pytest.approx(expected)


def test_state_layout_on_hand_built_scene():
    uavs = [[0, 0], [2, 2]]
    no_fly = [[5, 5]]
    targets = [[0, 0], [7, 3]]
    core, result = scene_core(uavs, no_fly, targets)
    state = result.state[0]
    cells = core.config.n_cells
    unknown, full = state[:cells], state[cells : 2 * cells]
    assert unknown[0].item() == pytest.approx(0.2) and full[0].item() == pytest.approx(0.8)  # target read F
    assert unknown[2 * 10 + 2].item() == pytest.approx(0.2) and full[22].item() == 0.0  # x-major: x*L2 + y
    assert unknown.sum().item() == pytest.approx(97 + 0.4)  # the no-fly cell (5, 5) is known: m(U) = 0
    assert unknown[5 * 10 + 5].item() == 0.0 and full[55].item() == 0.0
    scale = 9.0
    positions = state[2 * cells :].view(-1, 2) * scale
    assert positions.round().tolist() == [[0, 0], [2, 2], [5, 5], [0, 0], [7, 3]]
    image = result.state_map[0]
    assert image[0, 2, 2].item() == pytest.approx(0.2) and image[1, 0, 0].item() == pytest.approx(0.8)
    assert torch.equal(image.reshape(-1), state[: 2 * cells])


def test_uncertainty_reward_counts_each_cell_once():
    # Two UAVs fly onto the same unsensed cell (4, 5); a third onto another unsensed cell.
    core, _ = scene_core([[3, 5], [5, 5], [8, 8]], [], [[0, 9]], comm_range=0.0)
    result = core.step(torch.tensor([[1, 0, 0]]))
    r1, r2, r3, r4 = result.reward_terms[0].tolist()
    # (4, 5): 1 -> 0.04 after two negative readings; (7, 8): 1 -> 0.2.
    assert r1 == pytest.approx(0.96 + 0.8, abs=1e-5)
    assert r2 == 0 and r3 == 0
    assert r4 == -1.0  # the two UAVs on one cell are one pair within d2
    assert result.metrics["coverage"].item() == pytest.approx((3 + 2) / 100)
    assert result.reward.item() == pytest.approx(r1 + r2 + r3 + r4, abs=1e-6)


@pytest.mark.parametrize("rule", ["belief", "target"])
def test_discovery_reward_once_per_cell_and_false_discoveries_by_rule(rule):
    # UAV 0 oscillates over the target at (1, 1); UAV 1 oscillates over an empty cell with a sensor that
    # always reports "F" there (p_false_alarm = 1).
    core, result = scene_core(
        [[1, 1], [8, 8]], [], [[1, 1]], p_false_alarm=1.0, comm_range=0.0, discovery_rule=rule
    )
    assert result.metrics["targets_found"].item() == 0  # one reading gives m(F) = 0.8 < 0.95
    moves = [[1, 1], [0, 0], [1, 1], [0, 0]]  # away, back, away, back
    r2 = []
    for move in moves:
        result = core.step(torch.tensor([move]))
        r2.append(result.reward_terms[0, 1].item())
    # Every reading is "F", so each cell read twice reaches m(F) = 0.96 >= tau: at step 2 the target (1, 1)
    # and UAV 1's empty (8, 8), at step 3 the empty (2, 1) and (9, 8). eq. 24 (belief) pays each cell once,
    # an empty one "is considered to contain a target"; the target rule pays (1, 1) only.
    assert r2 == ([0.0, 2.0, 2.0, 0.0] if rule == "belief" else [0.0, 1.0, 0.0, 0.0])
    assert result.metrics["targets_found"].item() == 1
    assert result.metrics["false_discoveries"].item() == 3


def test_discovery_weight_scales_the_reward():
    core, _ = scene_core([[1, 1], [8, 8]], [], [[1, 1]], w_discovery=2.5, comm_range=0.0)
    core.step(torch.tensor([[1, 1]]))
    result = core.step(torch.tensor([[0, 0]]))
    assert result.reward_terms[0, 1].item() == 2.5


@pytest.mark.parametrize("rule", ["enter", "near"])
def test_a_uav_beside_a_zone_pays_only_under_near(rule):
    # No-fly zone at (5, 5). UAV 0 ends at (5, 6), beside it (distance 1 = d1); UAV 1 at (6, 6) (sqrt 2).
    core, _ = scene_core([[4, 6], [7, 7], [0, 0]], [[5, 5]], [[9, 9]], comm_range=0.0, safety_rule=rule)
    result = core.step(torch.tensor([[1, 4, 1]]))  # -> (5, 6), (6, 6), (1, 0)
    r3, r4 = result.reward_terms[0, 2:].tolist()
    charged = 1.0 if rule == "near" else 0.0  # enter: only distances < d1 = 1, i.e. the zone's own cell
    assert r3 == -charged and r4 == -charged  # (5, 6) and (6, 6) side by side: a collision under near only
    assert result.metrics["no_fly_violations"].item() == charged
    assert result.metrics["collisions"].item() == charged


def test_the_default_rule_is_the_papers_enter():
    assert scenario("map20").safety_rule == "enter"
    assert scenario("map10", safety_rule="near").violates(torch.tensor([1.0]), 1.0).item()
    assert not scenario("map10").violates(torch.tensor([1.0]), 1.0).item()


@pytest.mark.parametrize("rule", ["enter", "near"])
def test_a_uav_in_a_zone_and_co_located_uavs_pay_under_both_rules(rule):
    # UAV 0 ends on the zone (5, 5); UAV 1 too (so both are co-located); UAV 2 ends at (1, 0), far away.
    core, _ = scene_core(
        [[5, 4], [4, 6], [0, 0]], [[5, 5]], [[9, 9]], w_no_fly=2.0, w_collision=3.0, safety_rule=rule
    )
    result = core.step(torch.tensor([[3, 5, 1]]))  # -> (5, 5), (5, 5), (1, 0)
    r3, r4 = result.reward_terms[0, 2:].tolist()
    assert r3 == -4.0 and r4 == -3.0  # two (UAV, zone) pairs and one UAV pair; weights scale them
    assert result.metrics["no_fly_violations"].item() == 2 and result.metrics["collisions"].item() == 1


def test_safety_rule_is_validated_by_name():
    with pytest.raises(ValueError, match=r"safety_rule='inside': must be one of \['enter', 'near'\]"):
        scenario("map10", safety_rule="inside")


@pytest.mark.parametrize(
    "position,allowed",
    [
        ((0, 0), {1, 3, 6}),
        ((9, 9), {0, 2, 4}),
        ((0, 9), {1, 2, 5}),
        ((9, 0), {0, 3, 7}),
        ((0, 5), {1, 2, 3, 5, 6}),
        ((5, 9), {0, 1, 2, 4, 5}),
        ((5, 5), set(range(8))),
    ],
)
def test_action_masks_at_edges_and_corners(position, allowed):
    _, result = scene_core([list(position)], [], [])
    mask = result.action_mask[0, 0]
    assert set(mask.nonzero().squeeze(-1).tolist()) == allowed


def test_every_allowed_move_goes_where_eq1_says():
    moves = [(-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (1, -1), (1, 1), (-1, 1)]
    for action, (dx, dy) in enumerate(moves):
        core, _ = scene_core([[5, 5]], [], [])
        result = core.step(torch.tensor([[action]]))
        assert result.position[0, 0].tolist() == [5 + dx, 5 + dy]


def test_episode_is_truncated_after_exactly_T_steps_and_metrics_add_up():
    env = MCRSEnv("map10", num_envs=8)
    env.set_seed(1)
    generator = torch.Generator().manual_seed(1)
    td = env.reset()
    initial_uncertainty = td["metrics", "uncertainty"].clone()
    rewards, r1, steps = [], [], []
    for t in range(env.config.max_steps):
        td["agents", "action"] = random_allowed(td["agents", "action_mask"], generator)
        td = env.step(td)
        nxt = td["next"]
        assert nxt["truncated"].all() == (t == env.config.max_steps - 1)
        assert not nxt["terminated"].any() and torch.equal(nxt["done"], nxt["truncated"])
        rewards.append(nxt["reward"].squeeze(-1))
        r1.append(nxt["reward_terms"][:, 0])
        steps.append(nxt)
        td = td["next"]
    metrics = td["metrics"]
    assert torch.allclose(metrics["episode_reward"], torch.stack(rewards).sum(0), atol=1e-3)
    assert torch.allclose(torch.stack(r1).sum(0), initial_uncertainty - metrics["uncertainty"], atol=1e-3)
    cells = env.config.n_cells
    assert torch.allclose(metrics["uncertainty"], td["state"][:, :cells].sum(-1), atol=1e-3)
    sensed = (td["state_counts"].sum(-1) > 0).float().mean(-1)  # coverage: cells read, zones unread
    assert torch.allclose(metrics["coverage"], sensed)
    total_r2 = torch.stack([step["reward_terms"][:, 1] for step in steps]).sum(0)
    # eq. 24: r2 pays every cell reaching tau once, target or not.
    assert torch.equal(total_r2, metrics["targets_found"] + metrics["false_discoveries"])


def test_partial_reset_changes_only_the_masked_environments():
    env = MCRSEnv("map10", num_envs=3)
    env.set_seed(0)
    generator = torch.Generator().manual_seed(0)
    td = env.reset()
    for _ in range(5):
        td["agents", "action"] = random_allowed(td["agents", "action_mask"], generator)
        td = env.step(td)["next"]
    before = td.clone()
    # TorchRL's contract: the input carries the data of the environments that are not reset.
    td["_reset"] = torch.tensor([[True], [False], [True]])
    reset = env.reset(td)
    assert reset["step_count"].squeeze(-1).tolist() == [0, 5, 0]
    for key in [("agents", "observation"), ("agents", "position"), "state", ("metrics", "episode_reward")]:
        assert torch.equal(reset[key][1], before[key][1])
    assert reset["metrics", "episode_reward"][[0, 2]].eq(0).all()
    # The untouched environment steps on from where it was.
    reset["agents", "action"] = random_allowed(reset["agents", "action_mask"], generator)
    assert env.step(reset)["next", "step_count"].squeeze(-1).tolist() == [1, 6, 1]


def test_full_reset_restarts_every_environment():
    core = MCRSCore(scenario("map10", num_envs=4))
    generator = torch.Generator().manual_seed(0)
    result = core.reset()
    for _ in range(10):
        result = core.step(random_allowed(result.action_mask, generator))
    result = core.reset()
    assert result.step_count.eq(0).all() and result.metrics["collisions"].eq(0).all()
    # Only the N start cells are sensed, by one reading each, and UAVs start on distinct free cells.
    assert (core.counts.sum(-1) == 1).all() and (core.global_counts.sum(-1) == core.n_uavs).all()
    cells = result.position[..., 0] * 10 + result.position[..., 1]
    no_fly = core.no_fly_pos[..., 0] * 10 + core.no_fly_pos[..., 1]
    assert all(len(set(row)) == core.n_uavs for row in cells.tolist())
    assert not (cells.unsqueeze(-1) == no_fly.unsqueeze(-2)).any()
    targets = core.target_pos[..., 0] * 10 + core.target_pos[..., 1]
    assert not (targets.unsqueeze(-1) == no_fly.unsqueeze(-2)).any()
    assert (core.is_target.sum(-1) == core.config.n_targets).all()


def rollout(seed: int, name: str = "map15") -> TensorDict:
    env = MCRSEnv(name, num_envs=4)
    env.set_seed(seed)
    generator = torch.Generator().manual_seed(seed)
    td = env.reset()
    steps = []
    for _ in range(env.config.max_steps + 5):  # crosses an automatic reset
        td["agents", "action"] = random_allowed(td["agents", "action_mask"], generator)
        out, td = env.step_and_maybe_reset(td)
        steps.append(out)
    return torch.stack(steps, dim=1)


def test_same_seed_same_rollout_and_different_seed_differs():
    first, second = rollout(3), rollout(3)
    assert (first == second).all()
    assert not torch.equal(rollout(4)["next", "state"], first["next", "state"])


def test_state_memory_per_map20_environment_is_small():
    core = MCRSCore(scenario("map20", num_envs=16))
    per_env = core.state_nbytes() / 16
    assert per_env * 10_000 < 2 * 2**30


@pytest.mark.parametrize(
    "overrides,message",
    [
        ({"n_targets": 95, "n_no_fly": 10}, "n_targets + n_no_fly"),
        ({"n_uavs": 99, "n_no_fly": 3}, "n_uavs=99"),
        ({"m_f": 1.0}, "m_f=1.0: must be a probability in [0, 1)"),
        ({"m_e": -0.1}, "m_e"),
        ({"p_detect": 1.5}, "p_detect=1.5"),
        ({"p_false_alarm": -0.2}, "p_false_alarm"),
        ({"target_threshold": 2.0}, "target_threshold"),
        ({"comm_range": -1.0}, "comm_range=-1.0: must be a distance >= 0"),
        ({"sight_range": 0.0}, "sight_range"),
        ({"no_fly_safety": -1.0}, "no_fly_safety"),
        ({"uav_safety": float("nan")}, "uav_safety"),
        ({"comm_rounds": 0}, "comm_rounds=0: must be an integer >= 1 or 'flood'"),
        ({"comm_rounds": "all"}, "comm_rounds"),
        ({"invalid_action": "ignore"}, "invalid_action='ignore': must be one of ['raise', 'clip']"),
        ({"width": 0}, "width=0"),
        ({"max_steps": 2.5}, "max_steps"),
        ({"num_envs": 0}, "num_envs"),
        ({"w_collision": float("inf")}, "w_collision"),
        ({"device": "tpu"}, "device='tpu': is not a torch device"),
        ({"device": "meta"}, "device='meta': device type 'meta' is not supported"),
    ],
)
def test_bad_config_is_refused_naming_the_field(overrides, message):
    with pytest.raises(ValueError) as error:
        scenario("map10", **overrides)
    assert message in str(error.value)


def test_unknown_scenario_and_field_are_refused():
    with pytest.raises(
        ValueError,
        match=r"unknown scenario 'map30'; allowed: \['map10', 'map15', 'map20', 'map20_delay', 'map20_bandwidth', 'map20_dynamic'\]",
    ):
        scenario("map30")
    with pytest.raises(ValueError, match="unknown environment field"):
        scenario("map10", comm_radius=3)


def test_bad_actions_are_refused_naming_the_problem():
    core, _ = scene_core([[0, 0], [5, 5]], [], [])
    with pytest.raises(ValueError, match=r"shape \[num_envs, n_uavs\] = \[1, 2\]"):
        core.step(torch.tensor([1, 1, 1]))
    with pytest.raises(TypeError, match="integer dtype"):
        core.step(torch.tensor([[1.0, 1.0]]))
    with pytest.raises(ValueError, match=r"action\[0, 1\] = 8 is out of range: allowed 0..7"):
        core.step(torch.tensor([[1, 8]]))
    with pytest.raises(ValueError, match=r"action\[0, 0\] = 0 is masked.*allowed here: \[1, 3, 6\]"):
        core.step(torch.tensor([[0, 1]]))
    # Nothing moved: a refused step changes no state.
    assert core.uav_pos[0].tolist() == [[0, 0], [5, 5]] and core.step_count.item() == 0


def test_clip_mode_keeps_uavs_on_the_grid():
    core, _ = scene_core([[0, 0], [5, 5]], [], [], invalid_action="clip")
    result = core.step(torch.tensor([[4, 4]]))  # lower-left from the corner stays put
    assert result.position[0].tolist() == [[0, 0], [4, 4]]


def test_bad_scene_is_refused():
    with pytest.raises(ValueError, match="uav_positions must not be on no-fly cells"):
        scene_core([[1, 1]], [[1, 1]], [])
    with pytest.raises(ValueError, match="must lie on the 10 x 10 grid"):
        scene_core([[10, 1]], [], [])
    with pytest.raises(ValueError, match="uav_positions must be distinct"):
        scene_core([[1, 1], [1, 1]], [], [])


@pytest.mark.parametrize("device", available_devices())
def test_runs_on_every_available_device(device):
    env = MCRSEnv("map10", num_envs=5, device=device)
    env.set_seed(0)
    td = env.rollout(12, break_when_any_done=False)
    assert td.device.type == device and td["next", "reward"].device.type == device
    assert torch.isfinite(td["next", "reward"]).all()


def test_two_uavs_discovering_one_target_together_count_once():
    core, _ = scene_core([[4, 5], [6, 5], [0, 0]], [], [[5, 5]], comm_range=0.0)
    result = core.step(torch.tensor([[1, 0, 1]]))  # both onto the target (5, 5): two "F" readings at once
    assert result.reward_terms[0, 1].item() == 1.0
    assert result.metrics["targets_found"].item() == 1
    assert core.discovered[0, 5 * 10 + 5]
    result = core.step(torch.tensor([[0, 1, 3]]))  # away
    result = core.step(torch.tensor([[1, 0, 2]]))  # back: no second reward
    assert result.reward_terms[0, 1].item() == 0.0 and result.metrics["targets_found"].item() == 1


def test_discovery_counters_match_the_discovered_map_every_step():
    core = MCRSCore(scenario("map10", num_envs=64, p_detect=0.9, p_false_alarm=0.3))
    core.seed(5)
    generator = torch.Generator().manual_seed(5)
    result = core.reset()
    for _ in range(core.config.max_steps):
        result = core.step(random_allowed(result.action_mask, generator))
        found = (core.discovered & core.is_target).sum(-1).float()
        false = (core.discovered & ~core.is_target).sum(-1).float()
        assert torch.equal(result.metrics["targets_found"], found)
        assert torch.equal(result.metrics["false_discoveries"], false)
    assert result.metrics["targets_found"].max() <= core.config.n_targets


def test_stepping_past_the_time_limit_asks_for_a_reset():
    core = MCRSCore(scenario("map10", num_envs=2, max_steps=3, invalid_action="clip"))
    core.reset()
    for _ in range(3):
        core.step(torch.zeros(2, 4, dtype=torch.int64))
    with pytest.raises(RuntimeError, match=r"environment\(s\) \[0, 1\] reached the time limit max_steps=3"):
        core.step(torch.zeros(2, 4, dtype=torch.int64))
    core.reset(torch.tensor([True, True]))
    assert core.step(torch.zeros(2, 4, dtype=torch.int64)).step_count.tolist() == [1, 1]


def test_missing_cuda_is_refused_at_construction():
    if torch.cuda.is_available():
        with pytest.raises(ValueError, match=r"device='cuda:\d+': there are \d+ CUDA device"):
            scenario("map10", device=f"cuda:{torch.cuda.device_count()}")
    else:
        with pytest.raises(ValueError, match="device='cuda': CUDA is not available on this machine"):
            MCRSEnv("map10", device="cuda")


def test_torchrl_env_resets_to_a_scene_and_steps_on():
    env = MCRSEnv("map10", n_uavs=2, n_no_fly=1, n_targets=1, **EXACT_SENSOR)
    td = env.reset_to(torch.tensor([[0, 0], [5, 5]]), torch.tensor([[9, 9]]), torch.tensor([[1, 1]]))
    assert td["agents", "position"][0].tolist() == [[0, 0], [5, 5]]
    assert td["step_count"].item() == 0 and not td["done"].any()
    assert set(td["agents", "action_mask"][0, 0].nonzero().squeeze(-1).tolist()) == {1, 3, 6}
    td["agents", "action"] = torch.tensor([[6, 0]])  # upper-right onto the target (1, 1), left
    nxt = env.step(td)["next"]
    assert nxt["agents", "position"][0].tolist() == [[1, 1], [4, 5]]
    assert nxt["agents", "reading"][0].tolist() == [True, False]
