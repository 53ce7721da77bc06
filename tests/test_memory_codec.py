"""The state codec rebuilds the env's float32 state bit for bit from counts and cells."""

from __future__ import annotations

import pytest
import torch

from mcrs.env.belief import belief_masses
from mcrs.env.config import scenario
from mcrs.env.core import MCRSCore
from mcrs.memory.codec import StateCodec


def rollout(name: str, num_envs: int, seed: int, **overrides) -> tuple[torch.Tensor, torch.Tensor]:
    """States and state_counts ``[E, T+1, ...]`` of one whole episode per env, random allowed actions."""
    cfg = scenario(name, num_envs=num_envs, **overrides)
    core = MCRSCore(cfg)
    core.seed(seed)
    generator = torch.Generator().manual_seed(seed)
    result = core.reset()
    states, counts = [result.state], [result.state_counts]
    for _ in range(cfg.max_steps):
        scores = torch.rand(result.action_mask.shape, generator=generator).masked_fill(
            ~result.action_mask, -1
        )
        result = core.step(scores.argmax(-1))
        states.append(result.state)
        counts.append(result.state_counts)
    return torch.stack(states, 1), torch.stack(counts, 1)


@pytest.mark.parametrize("name", ["map10", "map15", "map20"])
def test_round_trip_is_bit_exact_on_real_rollouts(name: str) -> None:
    state, counts = rollout(name, num_envs=8, seed=3)
    codec = StateCodec(scenario(name))
    flat_state, flat_counts = state.flatten(0, 1), counts.flatten(0, 1)
    codes, positions = codec.encode(flat_counts, flat_state)
    assert codes.dtype == torch.uint8 and positions.dtype == torch.uint8
    assert codes.shape == (flat_state.shape[0], codec.n_cells, 2)
    assert positions.shape == (flat_state.shape[0], codec.n_positions, 2)
    assert torch.equal(codec.decode(codes, positions), flat_state)
    maps = codec.clear_zones(codec.decode_map(codes), positions)  # known zones: 0 whatever their counts
    assert torch.equal(maps, flat_state[:, : codec.map_dim])
    # The promoted storage decodes to the same bits.
    assert torch.equal(codec.decode(codes.to(torch.int16), positions), flat_state)
    # Into a reused buffer too.
    out = torch.full_like(flat_state, float("nan"))
    assert torch.equal(codec.decode(codes, positions, out=out), flat_state)


def test_long_rollout_with_high_counts_needs_int16_and_stays_exact() -> None:
    # Many UAVs on a tiny map for many steps: some cells are read more than 255 times.
    tiny = {"width": 2, "height": 2, "n_uavs": 4, "n_targets": 1, "n_no_fly": 0, "max_steps": 300}
    state, counts = rollout("map10", num_envs=2, seed=0, **tiny)
    assert counts.max() > 255
    codec = StateCodec(scenario("map10", **tiny))
    codes, positions = codec.encode(counts.flatten(0, 1), state.flatten(0, 1))
    assert codes.dtype == torch.int16
    assert torch.equal(codec.decode(codes, positions), state.flatten(0, 1))


def test_decode_table_equals_belief_masses_for_every_uint8_pair() -> None:
    """Every (positive, negative) pair of the uint8 table, against the env's function evaluated on tiny
    tensors (its scalar code path) - the table is built with the vectorised one."""
    codec = StateCodec(scenario("map10"))
    pairs = torch.stack(torch.meshgrid(torch.arange(256), torch.arange(256), indexing="ij"), -1).reshape(
        -1, 2
    )
    cells = codec.n_cells
    pad = (-pairs.shape[0]) % cells
    padded = torch.cat([pairs, torch.zeros(pad, 2, dtype=pairs.dtype)])
    codes = padded.to(torch.uint8).reshape(-1, cells, 2)
    maps = codec.decode_map(codes)
    unknown = maps[:, :cells].reshape(-1)[: pairs.shape[0]]
    full = maps[:, cells:].reshape(-1)[: pairs.shape[0]]
    expected_full, expected_unknown = [], []
    for chunk in pairs.split(5):  # 5 < one SIMD vector: the scalar path
        _, f, u = belief_masses(chunk[:, 0], chunk[:, 1], 0.8, 0.8)
        expected_full.append(f)
        expected_unknown.append(u)
    assert torch.equal(unknown, torch.cat(expected_unknown))
    assert torch.equal(full, torch.cat(expected_full))


@pytest.mark.parametrize("high", [300, 5000])
def test_int16_codes_decode_like_belief_masses(high: int) -> None:
    """Tables sized to the largest counts (300), and the direct computation beyond the table limit (5000)."""
    codec = StateCodec(scenario("map10", no_fly_prior="unknown"))  # maps of counts alone
    generator = torch.Generator().manual_seed(1)
    counts = torch.randint(0, high + 1, (6, codec.n_cells, 2), generator=generator)
    counts[0, 0] = torch.tensor([high, high])
    _, full, unknown = belief_masses(counts[..., 0], counts[..., 1], 0.8, 0.8)
    cells = torch.randint(0, 10, (6, codec.n_positions, 2), generator=generator)
    state = torch.cat([unknown, full, (cells.float() / 9.0).flatten(1)], 1)
    codes, positions = codec.encode(counts, state)
    assert codes.dtype == torch.int16
    assert torch.equal(codec.decode(codes, positions), state)


def test_bad_inputs_are_refused() -> None:
    codec = StateCodec(scenario("map10"))
    state, counts = rollout("map10", num_envs=2, seed=0)
    state, counts = state[:, 0], counts[:, 0]
    with pytest.raises(ValueError, match="state must have shape"):
        codec.encode(counts, state[:, :-1])
    with pytest.raises(ValueError, match="counts must have shape"):
        codec.encode(counts[:, :-1], state)
    with pytest.raises(ValueError, match="counts must be integers"):
        codec.encode(counts.float(), state)
    with pytest.raises(ValueError, match=r"counts must lie in \[0, 32767\]"):
        codec.encode(counts.int() - 1, state)
    shifted = state.clone()
    shifted[:, -1] += 0.01  # not a cell divided by the scale
    with pytest.raises(ValueError, match="state positions are not grid cells"):
        codec.encode(counts, shifted)


def test_identity_names_the_map_and_reports_mismatches() -> None:
    codec = StateCodec(scenario("map20"))
    identity = codec.identity()
    assert identity["map"] == "map20" and identity["width"] == 20 and identity["state_dim"] == 880
    assert codec.identity_mismatch(identity) is None
    other = StateCodec(scenario("map10")).identity()
    assert "width: saved 10, here 20" in codec.identity_mismatch(other)
    assert "m_f" in codec.identity_mismatch({**identity, "m_f": 0.7})


def test_torchrl_env_publishes_the_counts_behind_the_state_maps() -> None:
    from mcrs.env.torchrl_env import MCRSEnv

    env = MCRSEnv("map10", num_envs=3)
    env.set_seed(0)
    td = env.rollout(6, break_when_any_done=False)
    counts, state = td.get(("next", "state_counts")), td.get(("next", "state"))
    assert env.observation_spec["state_counts"].is_in(td[:, -1].get(("next", "state_counts")))
    cells = env.config.width * env.config.height
    _, full, unknown = belief_masses(counts[..., 0], counts[..., 1], env.config.m_f, env.config.m_e)
    zones = env.core.is_no_fly.unsqueeze(1)  # one episode: the same zones at every step; known, so 0
    unknown, full = unknown.masked_fill(zones, 0.0), full.masked_fill(zones, 0.0)
    assert torch.equal(unknown, state[..., :cells]) and torch.equal(full, state[..., cells : 2 * cells])
    assert int(counts.sum(-1).sum(-1)[0, -1]) == env.config.n_uavs * 7  # one reading per UAV per step


def test_known_zones_decode_as_zero_and_unread_zones_as_their_counts() -> None:
    """A zone cell entered (counts > 0) reads m(U) = m(F) = 0 in the state under known zones, its belief
    under unknown; both round trip, and a codec of the other reading refuses the maps."""
    scene = (torch.tensor([[4, 5], [0, 0], [9, 9], [0, 9]]), torch.tensor([[5, 5], [2, 7], [7, 2]]),
             torch.tensor([[1, 1], [2, 2], [3, 3], [6, 6], [8, 8], [1, 8]]))  # fmt: skip
    for prior in ("known", "unknown"):
        cfg = scenario("map10", no_fly_prior=prior)
        core = MCRSCore(cfg)
        core.reset_to(*scene)
        result = core.step(torch.tensor([[1, 1, 4, 5]]))  # UAV 0 into the zone (5, 5)
        state, counts = result.state, result.state_counts
        assert int(counts[0, 55].sum()) == 1
        assert (state[0, 55].item() == 0.0) == (prior == "known")
        codec = StateCodec(cfg)
        codes, positions = codec.encode(counts, state)
        assert torch.equal(codec.decode(codes, positions), state)
        other = StateCodec(scenario("map10", no_fly_prior="unknown" if prior == "known" else "known"))
        with pytest.raises(ValueError, match="state maps are not the beliefs of counts"):
            other.encode(counts, state)


def test_a_memory_saved_before_no_fly_prior_reads_as_unknown_zones() -> None:
    old = StateCodec(scenario("map10", no_fly_prior="unknown")).identity()
    del old["no_fly_prior"]
    assert StateCodec(scenario("map10", no_fly_prior="unknown")).identity_mismatch(old) is None
    assert "no_fly_prior" in StateCodec(scenario("map10")).identity_mismatch(old)
