"""The PettingZoo adapter: API compliance, seeding, spaces, errors, and that it runs the very same core."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from gymnasium import spaces
from gymnasium.utils.env_checker import data_equivalence
from pettingzoo.test import parallel_api_test, parallel_seed_test

from mcrs.env.config import SCENARIOS, scenario
from mcrs.env.core import METRICS
from mcrs.env.pettingzoo_env import MCRSParallelEnv
from mcrs.env.torchrl_env import MCRSEnv

# Paper table 2: (obs dim, state dim, N, T).
TABLE_2 = {"map10": (36, 226, 4, 50), "map15": (57, 502, 8, 70), "map20": (75, 880, 10, 100)}


def allowed_actions(observations: dict, rng: np.random.Generator) -> dict[str, int]:
    """A uniformly random allowed move per agent, read from the published action mask."""
    return {agent: int(rng.choice(np.flatnonzero(obs["action_mask"]))) for agent, obs in observations.items()}


def play_episode(env: MCRSParallelEnv, seed: int, action_seed: int) -> list[tuple]:
    """Every (observations, rewards, truncations, state, infos) of one full episode."""
    rng = np.random.default_rng(action_seed)
    observations, infos = env.reset(seed=seed)
    trace = [(observations, None, None, env.state().copy(), infos)]
    while env.agents:
        observations, rewards, _, truncations, infos = env.step(allowed_actions(observations, rng))
        trace.append((observations, rewards, truncations, env.state().copy(), infos))
    return trace


@pytest.mark.parametrize("name", SCENARIOS)
@pytest.mark.parametrize("invalid_action", ["clip", "raise"])
def test_parallel_api_test_passes(name: str, invalid_action: str) -> None:
    # parallel_api_test samples from the published action mask, so the strict "raise" config passes too.
    env = MCRSParallelEnv(name, invalid_action=invalid_action)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the API test reports most problems as warnings
        parallel_api_test(env, num_cycles=TABLE_2[name][3] + 10)
    assert env.agents == []  # both of its episodes ran to the time limit


@pytest.mark.parametrize("name", ["map10", "map20"])
def test_parallel_seed_test_passes(name: str) -> None:
    # The seed test samples actions without the mask: off-grid moves must be clipped.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        parallel_seed_test(lambda: MCRSParallelEnv(name, invalid_action="clip"))


@pytest.mark.parametrize("name", SCENARIOS)
def test_spaces_have_table_2_dimensions(name: str) -> None:
    obs_dim, state_dim, n_uavs, _ = TABLE_2[name]
    env = MCRSParallelEnv(name)
    assert env.possible_agents == [f"uav_{i}" for i in range(n_uavs)]
    for agent in env.possible_agents:
        space = env.observation_space(agent)
        assert space is env.observation_space(agent)
        assert isinstance(space, spaces.Dict)
        assert space["observation"].shape == (obs_dim,) and space["observation"].dtype == np.float32
        assert space["action_mask"].shape == (8,) and space["action_mask"].dtype == np.int8
        assert env.action_space(agent) == spaces.Discrete(8)
    assert env.state_space.shape == (state_dim,) and env.state_space.dtype == np.float32
    observations, _ = env.reset(seed=0)
    assert env.state().shape == (state_dim,)
    assert observations["uav_0"]["observation"].shape == (obs_dim,)


def test_full_episode_follows_the_parallel_conventions() -> None:
    env = MCRSParallelEnv("map15")  # default: invalid actions raise, so every action must respect the mask
    *_, max_steps = TABLE_2["map15"]
    trace = play_episode(env, seed=3, action_seed=4)
    assert len(trace) == max_steps + 1
    observations, _, _, state, infos = trace[0]
    assert set(observations) == set(infos) == set(env.possible_agents)
    for step, (observations, rewards, truncations, state, infos) in enumerate(trace):
        assert env.state_space.contains(state)
        for agent, obs in observations.items():
            assert env.observation_space(agent).contains(obs), (step, agent)
            # Flat and numeric (TorchRL's PettingZooWrapper stacks every entry into one tensor).
            assert infos[agent].keys() == {"reading", "position", *METRICS}
            assert all(type(infos[agent][name]) is float for name in METRICS)
            assert type(infos[agent]["reading"]) is bool
            x, y = infos[agent]["position"]
            # The observation's first two values are the normalised position (paper eq. 18).
            np.testing.assert_allclose(obs["observation"][:2], [x / 14, y / 14], rtol=1e-6)
            assert (obs["action_mask"] == 1).sum() >= 3
        if step == 0:
            continue
        assert len(set(rewards.values())) == 1  # the team reward, shared
        assert set(truncations.values()) == {step == max_steps}
    # Team rewards add up to the episode-reward metric.
    total = sum(rewards["uav_0"] for _, rewards, *_ in trace[1:])
    assert trace[-1][4]["uav_0"]["episode_reward"] == pytest.approx(total, rel=1e-5, abs=1e-4)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(dict.fromkeys(env.possible_agents, 0))


def test_terminations_are_always_false() -> None:
    env = MCRSParallelEnv("map10", invalid_action="clip", max_steps=5)
    env.reset(seed=0)
    seen = []
    while env.agents:
        _, _, terminations, truncations, _ = env.step(dict.fromkeys(env.agents, 1))
        seen.append((set(terminations.values()), set(truncations.values())))
    assert seen == [({False}, {False})] * 4 + [({False}, {True})]


def test_same_seed_replays_the_same_episode_and_another_seed_does_not() -> None:
    first = play_episode(MCRSParallelEnv("map10"), seed=11, action_seed=5)
    env = MCRSParallelEnv("map10")
    play_episode(env, seed=99, action_seed=0)  # a different episode in between must not matter
    second = play_episode(env, seed=11, action_seed=5)
    assert data_equivalence(first, second)
    other = play_episode(MCRSParallelEnv("map10"), seed=12, action_seed=5)
    assert not np.array_equal(first[0][3], other[0][3])


@pytest.mark.parametrize(
    "name,rule", [*((name, "enter") for name in SCENARIOS), ("map10", "near"), ("map20", "near")]
)
def test_matches_torchrl_env_over_a_full_episode(name: str, rule: str) -> None:
    """Same seed and actions give identical observations, states and rewards: it is the same core, under
    either penalty rule."""
    seed, agents = 21, [f"uav_{i}" for i in range(TABLE_2[name][2])]
    pz_env = MCRSParallelEnv(name, safety_rule=rule)
    rl_env = MCRSEnv(name, num_envs=1, safety_rule=rule)
    rl_env.set_seed(seed)
    td = rl_env.reset()
    observations, _ = pz_env.reset(seed=seed)
    rng = np.random.default_rng(0)
    steps = 0
    while True:
        np.testing.assert_array_equal(
            np.stack([observations[a]["observation"] for a in agents]), td["agents", "observation"][0].numpy()
        )
        np.testing.assert_array_equal(
            np.stack([observations[a]["action_mask"] for a in agents]).astype(bool),
            td["agents", "action_mask"][0].numpy(),
        )
        np.testing.assert_array_equal(pz_env.state(), td["state"][0].numpy())
        if not pz_env.agents:
            break
        actions = allowed_actions(observations, rng)
        td["agents", "action"] = torch.tensor([[actions[a] for a in agents]])
        td = rl_env.step(td)["next"]
        observations, rewards, _, truncations, infos = pz_env.step(actions)
        steps += 1
        assert rewards["uav_0"] == td["reward"].item()
        assert truncations["uav_0"] == td["truncated"].item()
        assert infos["uav_0"]["coverage"] == td["metrics", "coverage"].item()
        assert [infos[a]["reading"] for a in agents] == td["agents", "reading"][0].tolist()
        assert infos["uav_0"]["no_fly_violations"] == td["metrics", "no_fly_violations"].item()
    assert steps == TABLE_2[name][3]


def test_missing_or_unknown_agents_raise() -> None:
    env = MCRSParallelEnv("map10", invalid_action="clip")
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"missing agent\(s\) \['uav_1', 'uav_3'\]"):
        env.step({"uav_0": 0, "uav_2": 0})
    with pytest.raises(ValueError, match="uav_7"):
        env.step({**dict.fromkeys(env.agents, 0), "uav_7": 0})
    with pytest.raises(TypeError, match="integer"):
        env.step(dict.fromkeys(env.agents, 0.5))
    with pytest.raises(ValueError, match="out of range"):
        env.step(dict.fromkeys(env.agents, 8))


def test_invalid_actions_follow_the_config() -> None:
    moves = ((-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (1, -1), (1, 1), (-1, 1))
    strict, clipped = MCRSParallelEnv("map10"), MCRSParallelEnv("map10", invalid_action="clip")
    for seed in range(100):  # find a start with a UAV on the border, so that some move is masked
        observations, infos = strict.reset(seed=seed)
        masked = {a: np.flatnonzero(o["action_mask"] == 0) for a, o in observations.items()}
        if any(m.size for m in masked.values()):
            break
    actions = {a: int(m[0]) if m.size else int(np.flatnonzero(observations[a]["action_mask"])[0])
               for a, m in masked.items()}  # fmt: skip
    with pytest.raises(ValueError, match="masked"):
        strict.step(actions)

    _, start_infos = clipped.reset(seed=seed)
    assert start_infos == infos
    _, _, _, _, infos = clipped.step(actions)
    for agent, action in actions.items():
        x, y = start_infos[agent]["position"]
        dx, dy = moves[action]
        assert infos[agent]["position"] == (min(max(x + dx, 0), 9), min(max(y + dy, 0), 9))


def test_config_object_overrides_and_render_mode() -> None:
    env = MCRSParallelEnv(scenario("map15", num_envs=64), comm_range=2.0)
    assert env.core.num_envs == 1 and env.config.num_envs == 1
    assert env.config.comm_range == 2.0 and env.config.name == "map15"
    assert env.metadata["name"] == "mcrs_v0"
    assert env.render() is None  # no render_mode: nothing to draw, as PettingZoo asks
    with pytest.raises(ValueError, match=r"render_mode='video'.*allowed \[None, 'rgb_array', 'human'\]"):
        MCRSParallelEnv("map10", render_mode="video")
    with pytest.raises(RuntimeError, match="reset"):
        MCRSParallelEnv("map10").state()


# ------------------------------------------------------------------ TorchRL's PettingZooWrapper
def test_torchrl_pettingzoo_wrapper_runs_the_adapter() -> None:
    """TorchRL's own wrapper over the adapter: specs check, one group of agents, the action mask as
    TorchRL's ``action_mask`` (a whole episode of random actions under the strict config never picks a
    masked move), and the flat infos stacked per agent."""
    from torchrl.envs.libs.pettingzoo import PettingZooWrapper
    from torchrl.envs.utils import check_env_specs

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "tested with PettingZoo 1.24.3"
        env = PettingZooWrapper(
            MCRSParallelEnv("map10"), return_state=True, use_mask=False, categorical_actions=True, seed=0
        )
    check_env_specs(env)
    assert env.group_map == {"uav": [f"uav_{i}" for i in range(4)]}
    assert env.full_action_spec["uav", "action"].shape == (4,)
    torch.manual_seed(0)
    td = env.rollout(100, break_when_any_done=True)
    assert td.batch_size == (50,)  # the time limit of map10, then done
    assert td["next", "done"][-1].item() and not td["next", "done"][:-1].any()
    assert td["uav", "action_mask"].shape == (50, 4, 8) and td["state"].shape == (50, 226)
    info = td["next", "uav", "info"]
    assert set(info.keys()) == {"reading", "position", *METRICS}
    assert info["position"].shape == (50, 4, 2)
    # The running episode reward in the infos is the sum of the team rewards.
    total = td["next", "uav", "reward"][:, 0, 0].sum()
    assert info["episode_reward"][-1, 0].item() == pytest.approx(total.item(), rel=1e-5, abs=1e-4)


# ------------------------------------------------------------------ rendering
def test_rgb_array_render_draws_the_current_state() -> None:
    env = MCRSParallelEnv("map10", render_mode="rgb_array")
    with pytest.raises(RuntimeError, match="reset"):
        env.render()
    observations, _ = env.reset(seed=4)
    first = env.render()
    assert first.dtype == np.uint8 and first.ndim == 3 and first.shape[2] == 3
    assert first.shape[0] > 100 and first.shape[1] > 100 and first.std() > 10  # a picture, not a blank
    assert np.array_equal(env.render(), first)  # rendering does not change the state
    rng = np.random.default_rng(0)
    observations, *_ = env.step(allowed_actions(observations, rng))
    second = env.render()
    assert second.shape == first.shape and not np.array_equal(second, first)  # the UAVs moved
    # The same seed and actions draw the same frames (a fresh env, a fresh figure).
    again = MCRSParallelEnv("map10", render_mode="rgb_array")
    observations, _ = again.reset(seed=4)
    assert np.array_equal(again.render(), first)
    again.step(allowed_actions(observations, np.random.default_rng(0)))
    assert np.array_equal(again.render(), second)


def test_human_render_without_a_display_says_so(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr("sys.platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(RuntimeError, match=r'render_mode="human" needs a display.*rgb_array'):
        MCRSParallelEnv("map10", render_mode="human")


def test_human_render_with_a_display_but_no_window_backend_says_so(monkeypatch: pytest.MonkeyPatch) -> None:
    import matplotlib.pyplot as plt

    monkeypatch.setenv("DISPLAY", ":0")
    monkeypatch.setattr(plt, "get_backend", lambda: "agg")  # what a headless machine or MPLBACKEND=agg gives
    with pytest.raises(RuntimeError, match=r"interactive matplotlib backend.*MPLBACKEND"):
        MCRSParallelEnv("map10", render_mode="human")
