"""``env.far_view`` (beyond the paper): 8 window means of own m(U) appended to the observation.

Checked against a plain-Python reading of the definition (mcrs/env/far_view.py) on each UAV's own fused map,
and for what it must leave alone: with it off the observation is the paper's, and with it on the dynamics,
rewards and the rest of the observation are unchanged.
"""

from __future__ import annotations

import re

import pytest
import torch

from mcrs.env import MOVES, MCRSCore, scenario
from mcrs.env.belief import belief_masses
from mcrs.env.layout import ObservationLayout
from mcrs.env.pettingzoo_env import MCRSParallelEnv
from mcrs.env.torchrl_env import MCRSEnv
from tests.device_helpers import available_devices


def _walk(cfg, steps: int, seed: int, device: str = "cpu"):
    """The core after ``steps`` random allowed moves, and every step's result."""
    core = MCRSCore(cfg, device=device)
    core.seed(seed)
    g = torch.Generator().manual_seed(seed)
    results = [core.reset()]
    for _ in range(steps):
        mask = results[-1].action_mask.view(-1, 8).float().cpu()
        actions = torch.multinomial(mask, 1, generator=g).view(cfg.num_envs, cfg.n_uavs)
        results.append(core.step(actions.to(device)))
    return core, results


def _reference(unknown: torch.Tensor, position: torch.Tensor, k: int) -> torch.Tensor:
    """The definition, cell by cell: mean own m(U) over the (2k+1)^2 window centred k+1 cells along each move."""
    E, N, W, H = unknown.shape
    out = torch.zeros(E, N, 8)
    for e in range(E):
        for i in range(N):
            x, y = position[e, i].tolist()
            for a, (dx, dy) in enumerate(MOVES):
                cx, cy = x + (k + 1) * dx, y + (k + 1) * dy
                total = 0.0
                for u in range(cx - k, cx + k + 1):
                    for v in range(cy - k, cy + k + 1):
                        if 0 <= u < W and 0 <= v < H:
                            total += unknown[e, i, u, v].item()
                out[e, i, a] = total / (2 * k + 1) ** 2
    return out


@pytest.mark.parametrize(("name", "k", "steps"), [("map10", 1, 9), ("map10", 3, 20), ("map15", 2, 14)])
def test_far_view_is_the_window_means_of_own_uncertainty(name, k, steps):
    cfg = scenario(name, num_envs=2, far_view=k, expose_beliefs=True)
    layout = ObservationLayout.from_config(cfg)
    for result in _walk(cfg, steps, seed=k)[1][:: max(steps // 3, 1)]:
        own_unknown = result.belief_map[:, :, 0]  # each UAV's fused m(U), [E, N, W, H]
        expected = _reference(own_unknown, result.position, k)
        assert torch.allclose(layout.far_unknown_by_action(result.observation), expected, atol=1e-5)


@pytest.mark.parametrize("device", available_devices())
@pytest.mark.parametrize("evidence_decay", [0.0, 0.1])  # the lookup table's path and the formula's
def test_far_view_on_every_available_device(device, evidence_decay):
    cfg = scenario("map15", num_envs=3, far_view=2, evidence_decay=evidence_decay, expose_beliefs=True)
    layout = ObservationLayout.from_config(cfg)
    for result in _walk(cfg, 16, seed=5, device=device)[1][::5]:
        assert result.observation.device.type == device
        own_unknown, position = result.belief_map[:, :, 0].cpu(), result.position.cpu()
        far = layout.far_unknown_by_action(result.observation).cpu()
        assert torch.allclose(far, _reference(own_unknown, position, 2), atol=1e-5)


def test_far_view_leaves_the_dynamics_and_the_papers_observation_alone():
    paper, wide = scenario("map20", num_envs=3), scenario("map20", num_envs=3, far_view=2)
    assert paper.obs_dim + 8 == wide.obs_dim
    (_, plain), (_, extended) = _walk(paper, 30, seed=4), _walk(wide, 30, seed=4)
    layout = ObservationLayout.from_config(wide)
    assert ObservationLayout.from_config(paper).far_view == slice(paper.obs_dim, paper.obs_dim)
    for a, b in zip(plain, extended, strict=True):
        assert torch.equal(a.observation, b.observation[..., : paper.obs_dim])
        assert torch.equal(a.reward_terms, b.reward_terms) and torch.equal(a.position, b.position)
        assert layout.far_view.stop == wide.obs_dim
    # The windows see the map change: late in the episode UAVs have read ground around them.
    assert (
        extended[-1].observation[..., layout.far_view].mean()
        < extended[0].observation[..., layout.far_view].mean()
    )


def test_the_papers_observation_has_no_far_view_to_read():
    layout = ObservationLayout.from_config(scenario("map10"))
    with pytest.raises(ValueError, match="far_view=0"):
        layout.far_unknown_by_action(torch.zeros(1, layout.obs_dim))


def test_the_adapters_spaces_follow_the_longer_observation():
    cfg = scenario("map10", far_view=2)
    env = MCRSEnv(cfg.replace(num_envs=2))
    env.set_seed(0)
    td = env.rollout(5)
    assert (
        td["agents", "observation"].shape[-1]
        == cfg.obs_dim
        == env.observation_spec["agents", "observation"].shape[-1]
    )
    assert env.observation_spec["agents", "observation"].is_in(td[:, 0]["agents", "observation"])
    pz = MCRSParallelEnv(cfg)
    observations, _ = pz.reset(seed=0)
    agent = pz.agents[0]
    assert pz.observation_space(agent)["observation"].contains(observations[agent]["observation"])
    assert observations[agent]["observation"].shape == (cfg.obs_dim,)


@pytest.mark.parametrize(("value", "message"), [(-1, "must be an integer >= 0"), (1.5, "must be an integer >= 0"),
                                                 (True, "must be an integer >= 0"), (11, "must be <= max(width, height) = 10")])  # fmt: skip
def test_bad_far_view_is_refused_by_name(value, message):
    with pytest.raises(ValueError, match=re.escape(f"far_view={value!r}: {message}")):
        scenario("map10", far_view=value)


@pytest.mark.parametrize(
    "overrides",
    [{"evidence_decay": 0.05}, {"max_steps": 600}],  # float counts; a table too large to build
    ids=["decayed_counts", "no_table"],
)
def test_far_view_without_the_lookup_table_is_the_same_definition(overrides):
    """m(U) comes from a lookup table of integer counts where one fits; decayed counts, or a team and horizon
    whose table would be too large, compute it from the counts: the same window means either way."""
    cfg = scenario("map10", num_envs=2, far_view=2, expose_beliefs=True, **overrides)
    core, results = _walk(cfg, 12, seed=1)
    assert core.far_view.table is None
    layout = ObservationLayout.from_config(cfg)
    expected = _reference(results[-1].belief_map[:, :, 0], results[-1].position, 2)
    assert torch.allclose(layout.far_unknown_by_action(results[-1].observation), expected, atol=1e-5)


def test_the_lookup_table_is_belief_masses_of_every_count_pair():
    core = MCRSCore(scenario("map10", far_view=1))
    table, stride = core.far_view.table, core.far_view.stride
    assert table is not None and table.numel() == stride**2 == (4 * 51 + 1) ** 2
    positive, negative = torch.tensor([0, 0, 3, 7, 204]), torch.tensor([0, 5, 2, 7, 204])
    expected = belief_masses(positive, negative, 0.8, 0.8)[2]
    assert torch.equal(table[positive * stride + negative], expected)
