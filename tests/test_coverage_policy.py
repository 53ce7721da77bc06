"""The coverage heuristic: the lawnmower's strips, detouring around the cells r3 charges (both readings)."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDictBase

from mcrs.env import MOVES, MCRSEnv, scenario
from mcrs.env.config import EnvConfig
from mcrs.policies import POLICIES, CoveragePolicy, make_policy
from mcrs.policies.base import ACTION, ACTION_MASK
from mcrs.policies.coverage import charged_offsets
from tests.device_helpers import available_devices

RULES = ("enter", "near")
# map10 (strips x in [0, 2), [2, 5), [5, 7), [7, 10)): each UAV starts at the foot of its strip, and each
# zone lies on a strip's snake, so the lawnmower flies through all three.
UAVS = [[0, 0], [2, 0], [5, 0], [7, 0]]
ZONES = [[0, 5], [3, 7], [9, 9]]
TARGETS = [[1, 1], [4, 4], [6, 2], [8, 8], [2, 9], [5, 5]]
FAR_ZONES = [[9, 9], [8, 2], [6, 6]]  # out of sight of column 0 below y = 8
MOVE = torch.tensor(MOVES)


def _play(
    env: MCRSEnv, policy: CoveragePolicy | None, td: TensorDictBase, steps: int, name: str = "coverage"
) -> dict[str, torch.Tensor]:
    """Step ``env`` from ``td``; positions ``[E, T+1, N, 2]``, actions and masks ``[E, T, N(, 8)]``, and the
    final metrics (on the CPU)."""
    policy = policy if policy is not None else make_policy(name, env.config, 0)
    positions, actions, masks = [td.get(("agents", "position"))], [], []
    with torch.no_grad():
        for _ in range(steps):
            masks.append(td.get(ACTION_MASK))
            td = policy(td)
            actions.append(td.get(ACTION))
            td = env.step(td.select(ACTION))["next"]
            positions.append(td.get(("agents", "position")))
    return {
        "position": torch.stack(positions, 1).cpu(),
        "action": torch.stack(actions, 1).cpu(),
        "mask": torch.stack(masks, 1).cpu(),
        "metrics": td.get("metrics").cpu(),
    }


def _scene(rule: str, zones: list[list[int]] = ZONES, uavs: list[list[int]] = UAVS, **overrides) -> tuple:
    cfg = scenario("map10", safety_rule=rule, **overrides)
    env = MCRSEnv(cfg)
    td = env.reset_to(torch.tensor(uavs), torch.tensor(zones), torch.tensor(TARGETS))
    return cfg, env, td


def _charged(cfg: EnvConfig, cells: torch.Tensor, zones: torch.Tensor) -> torch.Tensor:
    """``[...]``: zones whose r3 charges a UAV on each cell of ``cells [..., 2]`` (zones ``[Z, 2]``)."""
    squared = (cells.unsqueeze(-2) - zones).pow(2).sum(-1).to(torch.float32)
    return cfg.violates(squared, cfg.no_fly_safety).sum(-1)


def test_registered_as_a_heuristic() -> None:
    assert POLICIES["coverage"] is CoveragePolicy
    assert isinstance(make_policy("coverage", scenario("map10"), 0), CoveragePolicy)


@pytest.mark.parametrize("rule", RULES)
def test_steps_around_zones_on_its_strip(rule: str) -> None:
    cfg, env, td = _scene(rule)
    lawnmower = _play(env, None, td, cfg.max_steps, name="lawnmower")
    assert lawnmower["metrics"]["no_fly_violations"].item() >= 3  # the scene does put zones on the paths

    cfg, env, td = _scene(rule)
    played = _play(env, None, td, cfg.max_steps)
    assert played["metrics"]["no_fly_violations"].item() == 0
    path = played["position"][0]  # [T+1, N, 2]
    assert (_charged(cfg, path, torch.tensor(ZONES)) == 0).all()
    # It went around, not back: UAV 0 got past the zone at (0, 5) to the top of its strip.
    visited = {tuple(cell) for cell in path[:, 0].tolist()}
    assert {(0, 9), (1, 9)} & visited
    neighbours = {(0, 4), (0, 6), (1, 5)}  # of (0, 5), on UAV 0's snake
    if rule == "near":  # charged too: never entered
        assert not neighbours & visited
    else:  # free under "enter": the rule is read from the config, so the snake still passes them
        assert neighbours & visited
    # Detours cost no coverage: it senses nearly every cell it may enter (lawnmower: every cell).
    grid = torch.cartesian_prod(torch.arange(cfg.width), torch.arange(cfg.height))
    free = (_charged(cfg, grid, torch.tensor(ZONES)) == 0).float().mean().item()  # 0.97, near: 0.88
    assert played["metrics"]["coverage"].item() >= free - 0.03


@pytest.mark.parametrize("rule", RULES)
def test_enters_a_charged_cell_only_when_every_allowed_move_is_charged(rule: str) -> None:
    cfg = scenario("map15", safety_rule=rule, num_envs=6)
    env = MCRSEnv(cfg)
    env.set_seed(5)
    td = env.reset()
    zones = env.core.no_fly_pos.clone().cpu()  # [E, Z, 2] the truth, which the policy never reads
    played = _play(env, None, td, cfg.max_steps)
    start = played["position"][:, :-1]  # [E, T, N, 2]
    destination = start.unsqueeze(-2) + MOVE  # [E, T, N, 8, 2]
    charged = _charged(cfg, destination, zones.view(cfg.num_envs, 1, 1, 1, -1, 2))  # [E, T, N, 8]
    free = played["mask"] & (charged == 0)
    taken = charged.gather(-1, played["action"].unsqueeze(-1)).squeeze(-1)
    assert not ((taken > 0) & free.any(-1)).any()
    assert played["metrics"]["no_fly_violations"].sum() == taken.sum()  # every charge was forced


def test_keeps_off_a_cell_where_a_visible_uav_is() -> None:
    uavs = [[0, 0], [0, 1], [5, 0], [7, 0]]  # UAV 1 sits on UAV 0's next snake cell
    cfg, _, td = _scene("enter", zones=FAR_ZONES, uavs=uavs)
    up = MOVES.index((0, 1))
    assert make_policy("lawnmower", cfg, 0)(td.clone()).get(ACTION)[0, 0].item() == up
    assert make_policy("coverage", cfg, 0)(td).get(ACTION)[0, 0].item() != up


def test_actions_always_allowed_by_the_mask() -> None:
    cfg, env, td = _scene("near", uavs=[[0, 4], [2, 0], [5, 0], [7, 0]])
    mask = torch.zeros_like(td.get(ACTION_MASK))
    up = MOVES.index((0, 1))
    mask[..., up] = True  # only "up", into the zone at (0, 5), is allowed to UAV 0: it must take it
    td.set(ACTION_MASK, mask)
    assert (make_policy("coverage", cfg, 0)(td).get(ACTION) == up).all()
    # The env's own masks, with the shield removing charged moves: the env raises on a masked action.
    cfg = scenario("map20", safety_rule="near", no_fly_shield=True, num_envs=3)
    assert cfg.invalid_action == "raise"
    env = MCRSEnv(cfg)
    env.set_seed(2)
    played = _play(env, None, env.reset(), 30)
    assert played["mask"].gather(-1, played["action"].unsqueeze(-1)).all()


def test_same_seed_same_actions() -> None:
    def actions(seed: int) -> torch.Tensor:
        cfg = scenario("map10", num_envs=4)
        env = MCRSEnv(cfg)
        env.set_seed(9)
        return _play(env, make_policy("coverage", cfg, seed), env.reset(), cfg.max_steps)["action"]

    assert torch.equal(actions(3), actions(3))


def test_memory_restarts_at_a_new_episode() -> None:
    """A policy reused after an episode acts like a fresh one: no remembered zone or pointer carries over."""
    cfg, env, td = _scene("near")
    used = make_policy("coverage", cfg, 0)
    _play(env, used, td, 20)  # UAV 0 has seen the zone at (0, 5) and walked around it
    assert used.zone_known[0, 0, 0]
    used.generator.manual_seed(0)  # the tie-breaks' draws as a fresh policy's: only the memory differs
    td = env.reset_to(torch.tensor(UAVS), torch.tensor(FAR_ZONES), torch.tensor(TARGETS))
    again = _play(env, used, td, 12)
    cfg, env, td = _scene("near", zones=FAR_ZONES)
    fresh = _play(env, None, td, 12)
    assert torch.equal(again["action"], fresh["action"])
    # Zone 0 moved out of sight: a stale memory would have walked around (0, 5) again.
    assert (0, 5) in {tuple(cell) for cell in again["position"][0, :, 0].tolist()}


@pytest.mark.parametrize("device", available_devices())
def test_runs_on_any_device(device: str) -> None:
    cfg = scenario("map10", num_envs=2, device=device)
    env = MCRSEnv(cfg)
    env.set_seed(0)
    td = env.reset()
    policy = make_policy("coverage", cfg, 0)
    action = policy(td).get(ACTION)
    assert action.device.type == torch.device(device).type and action.dtype == torch.int64
    played = _play(env, policy, td, 10)
    assert played["mask"].gather(-1, played["action"].unsqueeze(-1)).all()


@pytest.mark.parametrize(
    ("rule", "distance", "cells"),
    [("enter", 1.0, {(0, 0)}), ("near", 1.0, {(0, 0), (1, 0), (-1, 0), (0, 1), (0, -1)})],
)
def test_charged_offsets_follow_the_rule(rule: str, distance: float, cells: set[tuple[int, int]]) -> None:
    kernel = charged_offsets(scenario("map10", safety_rule=rule, no_fly_safety=distance))[0, 0]
    r = kernel.shape[-1] // 2
    assert {(int(x) - r, int(y) - r) for x, y in kernel.nonzero().tolist()} == cells
