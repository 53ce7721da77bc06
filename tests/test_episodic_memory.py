"""D_E: Algorithm 1 exactly (against a plain sequential reference), eviction, look-ups, re-embedding,
EMU counters, promotion and persistence."""

from __future__ import annotations

import pytest
import torch
from mcrs_benchmarks.memory import rollout as env_rollout
from torch import nn

from mcrs.env.config import scenario
from mcrs.memory import EpisodicMemory, InsertStats, StateCodec, discounted_returns, resolution
from mcrs.memory.index import squared_distance

INF = float("inf")


# ---------------------------------------------------------------------------------------------- helpers
class KeyInState(nn.Module):
    """Test embedding: the key is written in the first ``key_dim`` values of the state (time ignored)."""

    def __init__(self, key_dim: int = 4) -> None:
        super().__init__()
        self.key_dim = key_dim

    def forward(self, state: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        return state[..., : self.key_dim].clone()


class TinyNet(nn.Module):
    """A small random MLP embedding of (state, t/T)."""

    def __init__(self, state_dim: int, key_dim: int = 4, seed: int = 0) -> None:
        super().__init__()
        self.key_dim = key_dim
        generator = torch.Generator().manual_seed(seed)
        self.w1 = nn.Parameter(torch.randn(state_dim + 1, 16, generator=generator) / state_dim**0.5)
        self.w2 = nn.Parameter(torch.randn(16, key_dim, generator=generator))

    def forward(self, state: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        x = torch.cat([state, time.unsqueeze(-1)], -1)
        return torch.tanh(x @ self.w1) @ self.w2


MAP10 = scenario("map10")


def synthetic_batch(keys: torch.Tensor, config=MAP10, seed: int = 0):
    """``keys [E, T, k]`` written into otherwise valid-looking states, with random counts and cells."""
    E, T, k = keys.shape
    generator = torch.Generator().manual_seed(seed)
    codec = StateCodec(config)
    state = torch.zeros(E, T, config.state_dim)
    state[..., :k] = keys
    cells = torch.randint(0, config.width, (E, T, codec.n_positions, 2), generator=generator)
    state[..., codec.map_dim :] = (cells.float() / (config.width - 1)).flatten(2)
    counts = torch.randint(0, 6, (E, T, config.n_cells, 2), generator=generator, dtype=torch.int16)
    return state, counts


def rollout(name: str, num_envs: int, seed: int):
    """A collector-like batch of whole episodes: states s_0..s_{T-1}, their counts, rewards r_t."""
    return env_rollout(scenario(name), num_envs, seed)


class Reference:
    """Algorithm 1 as written: one transition at a time, brute-force nearest key, plain Python control.

    Same conventions as the memory: transitions episode by episode, backwards in time; FIFO ring with the
    batch's eviction first; within delta = float32 squared distance on standardised keys strictly below
    float32(delta^2) (ball) or every |difference| <= float32(delta) (box); nearest = smallest squared
    distance, lowest slot on ties; EMU counters, optimality propagation and counter reset as documented.
    """

    def __init__(
        self,
        capacity: int,
        delta: float,
        gamma: float,
        max_steps: int,
        track: bool,
        k: int = 4,
        shape: str = "ball",
        counter_reset: bool = False,
    ):
        self.C, self.gamma, self.T, self.track = capacity, gamma, max_steps, track
        self.shape, self.counter_reset = shape, counter_reset
        self.delta = torch.tensor(delta, dtype=torch.float32)
        self.delta_sq = torch.tensor(delta * delta, dtype=torch.float32)
        self.keys = torch.zeros(capacity, k)
        self.H = torch.zeros(capacity)
        self.step = torch.zeros(capacity, dtype=torch.int16)
        self.live = torch.zeros(capacity, dtype=torch.bool)
        self.source: dict[int, tuple[int, int, int]] = {}  # slot -> (batch number, e, t)
        self.n_call = [0] * capacity
        self.n_xi = [0] * capacity
        self.xi = [False] * capacity
        self.start = self.size = 0
        self.batches = 0

    def insert(self, keys, reward, desirable, mean, std):
        E, T, _ = keys.shape
        evict = max(0, self.size + E * T - self.C)
        for i in range(evict):
            self.live[(self.start + i) % self.C] = False
        self.start, self.size = (self.start + evict) % self.C, self.size - evict
        if self.size == 0:  # statistics from the batch's keys
            flat = keys.reshape(-1, keys.shape[-1]).double()
            mean = flat.mean(0).float()
            std = flat.std(0, correction=0).clamp(min=1e-6).float()
        R = torch.zeros(E)
        returns = torch.zeros(E, T)
        for t in reversed(range(T)):
            R = reward[:, t] + self.gamma * R
            returns[:, t] = R
        stats = {"new": 0, "hits": 0, "shifted": 0}
        for e in range(E):
            want = bool(desirable[e]) if self.track else False
            for t in reversed(range(T)):
                x, r = keys[e, t], returns[e, t]
                zq, zs = ((x - mean) / std)[None], (self.keys - mean) / std
                d2 = squared_distance(zq, zs)
                within = (zq - zs).abs().amax(-1) <= self.delta if self.shape == "box" else d2 < self.delta_sq
                d2 = torch.where(self.live & within, d2, torch.full_like(d2, INF))
                if torch.isinf(d2.min()):
                    s = (self.start + self.size) % self.C
                    self.size += 1
                    self.live[s] = True
                    self.keys[s], self.H[s], self.step[s] = x, r, t
                    self.source[s] = (self.batches, e, t)
                    self.n_call[s], self.n_xi[s], self.xi[s] = 1, int(want), want
                    stats["new"] += 1
                    continue
                s = int(d2.argmin())  # first minimum: lowest slot
                stats["hits"] += 1
                if self.track:
                    self.n_call[s] += 1
                    self.n_xi[s] += int(want)
                desirability_shift = self.track and want and not self.xi[s]
                if self.H[s] < r or desirability_shift:
                    stats["shifted"] += 1
                    self.keys[s], self.H[s], self.step[s] = x, r, t
                    self.source[s] = (self.batches, e, t)
                    self.xi[s] = self.xi[s] or want
                    if desirability_shift and self.counter_reset:
                        self.n_call[s], self.n_xi[s] = 1, 1
                if self.track and self.xi[s]:  # EMU: the earlier states of this episode are desirable
                    want = True
        self.batches += 1
        stats["evicted"] = evict
        return stats


def assert_same(memory: EpisodicMemory, ref: Reference, batches: list) -> None:
    """Every slot of the memory holds exactly what the reference holds."""
    assert memory.size == ref.size and memory.start == ref.start
    assert torch.equal(memory.live, ref.live)
    live = ref.live
    assert torch.equal(memory.keys[live], ref.keys[live])
    assert torch.equal(memory.returns[live], ref.H[live])
    assert torch.equal(memory.step[live], ref.step[live])
    for s in live.nonzero().squeeze(1).tolist():
        b, e, t = ref.source[s]
        codes, positions = batches[b]
        assert torch.equal(memory.codes[s].to(torch.int32), codes[e, t].to(torch.int32)), s
        assert torch.equal(memory.positions[s], positions[e, t])
    if ref.track:
        assert memory.n_call[live].tolist() == [ref.n_call[s] for s in live.nonzero().squeeze(1).tolist()]
        assert memory.n_xi[live].tolist() == [ref.n_xi[s] for s in live.nonzero().squeeze(1).tolist()]
        assert memory.xi[live].tolist() == [ref.xi[s] for s in live.nonzero().squeeze(1).tolist()]


def run_both(memory: EpisodicMemory, ref: Reference, state, counts, reward, desirable=None, batches=None):
    """Insert into both; compare the stats and every slot."""
    keys = memory.embedding(
        state, memory.normalised_time(torch.arange(state.shape[1])).expand(state.shape[:2])
    )
    mean, std = memory.index.mean.clone(), memory.index.std.clone()
    stats = memory.insert(state, counts, reward, desirable)
    expected = ref.insert(keys.detach(), reward, desirable, mean, std)
    assert stats == InsertStats(
        transitions=state.shape[0] * state.shape[1],
        new=expected["new"],
        hits=expected["hits"],
        shifted=expected["shifted"],
        evicted=expected["evicted"],
    )
    codec = memory.codec
    E, T = state.shape[:2]
    codes, positions = codec.encode(
        counts.reshape(E * T, -1, 2), state.reshape(E * T, -1), check_maps=memory.check_states
    )
    batches.append((codes.view(E, T, *codes.shape[1:]), positions.view(E, T, *positions.shape[1:])))
    assert_same(memory, ref, batches)
    return stats


def brute_lookup(memory: EpisodicMemory, keys: torch.Tensor):
    z, stored = memory.index.standardise(keys)[:, None], memory.index.standardise(memory.keys)[None]
    d2 = squared_distance(z, stored)
    if memory.index.shape == "box":
        within = (z - stored).abs().amax(-1) <= memory.index.tolerance_f32
    else:
        within = d2 < memory.index.tolerance_sq
    d2 = torch.where(memory.live & within, d2, torch.full_like(d2, INF))
    best, slot = d2.min(1)
    hit = torch.isfinite(best)
    return torch.where(hit, memory.returns[slot], 0.0), hit, torch.where(hit, slot, -1)


def clustered_keys(E: int, T: int, clusters: int, spread: float, generator: torch.Generator) -> torch.Tensor:
    """Keys drawn around few centres, ``spread`` (in std units of the centres) apart: many interactions."""
    centres = torch.randn(clusters, 4, generator=generator)
    pick = torch.randint(0, clusters, (E, T), generator=generator)
    keys = centres[pick] + torch.randn(E, T, 4, generator=generator) * spread
    exact = torch.rand(E, T, generator=generator) < 0.1  # some exact repeats of a centre
    return torch.where(exact.unsqueeze(-1), centres[pick], keys)


# ------------------------------------------------------------------------------------- arguments
@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"tolerance": 0.0}, r"tolerance must be a finite number > 0, got 0.0"),
        ({"tolerance": -1e-3}, r"tolerance must be a finite number > 0"),
        ({"capacity": 0}, r"capacity must be an int in \[1, "),
        ({"gamma": 1.5}, r"gamma must be a number in \[0, 1\], got 1.5"),
        ({"gamma": -0.1}, r"gamma must be a number in \[0, 1\]"),
        ({"max_steps": 0}, r"max_steps must be an int in \[1, "),
        ({"stale_fraction": 0}, r"stale_fraction must be a number > 0"),
    ],
)
def test_bad_arguments_are_refused_naming_the_argument(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        EpisodicMemory(KeyInState(), StateCodec(MAP10), **kwargs)


def test_embedding_without_key_dim_is_refused() -> None:
    with pytest.raises(ValueError, match=r"embedding.key_dim must be an int in \[1, 8\]"):
        EpisodicMemory(nn.Identity(), StateCodec(MAP10))


def test_discounted_returns_walk_backwards() -> None:
    reward = torch.tensor([[1.0, 0.0, 2.0, 4.0]])
    assert torch.equal(discounted_returns(reward, 0.5), torch.tensor([[2.0, 2.0, 4.0, 4.0]]))


# ----------------------------------------------------------------------------------- Algorithm 1
def hand_memory(**kwargs) -> EpisodicMemory:
    return EpisodicMemory(
        KeyInState(), StateCodec(MAP10), capacity=20, tolerance=0.01, gamma=0.5, check_states=False, **kwargs
    )


# Four keys whose per-dimension mean is 0 and std 1: the first batch's statistics make z == x.
BASE = torch.tensor([[1.0, 1, 1, 1], [-1, -1, -1, -1], [1, -1, 1, -1], [-1, 1, -1, 1]])


def test_each_branch_of_algorithm_1() -> None:
    memory = hand_memory()
    # Episode of T=4; backwards: t=3 -> BASE[0], t=2 -> BASE[1], ...; rewards give R = (1, 2, 4, 8).
    keys = BASE.flip(0).unsqueeze(0)  # keys[0, t] = BASE[3 - t]
    reward = torch.tensor([[0.0, 0.0, 0.0, 8.0]])
    stats = memory.insert(*synthetic_batch(keys), reward)
    assert stats == InsertStats(transitions=4, new=4, hits=0, shifted=0, evicted=0)  # new keys
    assert torch.equal(memory.index.mean, torch.zeros(4)) and torch.equal(memory.index.std, torch.ones(4))
    assert torch.equal(memory.keys[:4], BASE)  # slots in transition order
    assert memory.returns[:4].tolist() == [8.0, 4.0, 2.0, 1.0] and memory.step[:4].tolist() == [3, 2, 1, 0]

    close = torch.tensor([0.004, -0.004, 0.004, -0.004])  # |close| = 0.008 < delta = 0.01
    keys = torch.stack([BASE[3] + 2 * close, BASE[2] + 3, BASE[1] + close, BASE[0] + close]).unsqueeze(0)
    # R = (t0: 2.5, t1: 5, t2: 10, t3: 4). Backwards: t3 meets BASE[0] (H 8 > 4: nothing), t2 meets
    # BASE[1] (H 4 < 10: shift), t1 is far (new), t0 is 0.016 from BASE[3] (outside delta: new).
    reward = torch.tensor([[0.0, 0.0, 8.0, 4.0]])
    state, counts = synthetic_batch(keys, seed=1)
    stats = memory.insert(state, counts, reward)
    assert stats == InsertStats(transitions=4, new=2, hits=2, shifted=1, evicted=0)
    assert torch.equal(memory.keys[0], BASE[0]) and memory.returns[0] == 8.0  # lower return: unchanged
    assert memory.step[0] == 3
    assert torch.equal(memory.keys[1], BASE[1] + close) and memory.returns[1] == 10.0 and memory.step[1] == 2
    codes, positions = memory.codec.encode(counts[0], state[0], check_maps=False)
    assert torch.equal(memory.codes[1], codes[2]) and torch.equal(
        memory.positions[1], positions[2]
    )  # state shifted
    assert torch.equal(memory.keys[4], BASE[2] + 3) and memory.returns[4] == 5.0  # new entries, in order
    assert torch.equal(memory.keys[5], BASE[3] + 2 * close) and memory.returns[5] == 2.5
    assert len(memory) == 6


def test_equal_return_does_not_shift_and_a_batch_sees_its_own_entries() -> None:
    memory = hand_memory()
    # One episode: t=1 and t=0 have the same key; walking backwards t=1 creates it, t=0 finds it.
    keys = torch.stack([BASE[0], BASE[0]]).unsqueeze(0)
    stats = memory.insert(*synthetic_batch(keys), torch.tensor([[2.0, 0.0]]))  # R = (2, 0)
    assert stats == InsertStats(transitions=2, new=1, hits=1, shifted=1, evicted=0)
    assert memory.returns[0] == 2.0 and memory.step[0] == 0
    stats = memory.insert(*synthetic_batch(keys), torch.tensor([[2.0, 0.0]]))
    assert stats.shifted == 0 and stats.hits == 2  # equal returns: H < R is false


def test_a_shift_hides_the_old_key_from_later_transitions() -> None:
    """Two transitions 0.018 apart (not within delta of each other) share a stored neighbour: the first
    shifts it away, so the second finds nothing and makes a new entry."""
    memory = hand_memory()
    memory.insert(*synthetic_batch(BASE.flip(0).unsqueeze(0)), torch.tensor([[0.0, 0.0, 0.0, 8.0]]))
    nudge = torch.tensor([0.009, 0.0, 0.0, 0.0])
    keys = torch.stack([BASE[1] - nudge, BASE[1] + nudge]).unsqueeze(0)  # t=1 goes first
    stats = memory.insert(*synthetic_batch(keys), torch.tensor([[0.0, 10.0]]))  # R = (5, 10)
    assert stats == InsertStats(transitions=2, new=1, hits=1, shifted=1, evicted=0)
    assert torch.equal(memory.keys[1], BASE[1] + nudge) and memory.returns[1] == 10.0
    assert torch.equal(memory.keys[4], BASE[1] - nudge) and memory.returns[4] == 5.0


def test_equidistant_entries_resolve_to_the_lowest_slot() -> None:
    memory = hand_memory()
    memory.insert(*synthetic_batch(BASE.flip(0).unsqueeze(0)), torch.tensor([[0.0, 0.0, 0.0, 8.0]]))
    q, e = torch.full((4,), 3.0), torch.tensor([2.0**-7, 0.0, 0.0, 0.0])
    memory.insert(*synthetic_batch(torch.stack([q - e, q + e]).unsqueeze(0)), torch.zeros(1, 2))
    assert torch.equal(memory.keys[4], q + e) and torch.equal(memory.keys[5], q - e)
    _, _, slot = memory.lookup_keys(q.unsqueeze(0))
    assert slot.tolist() == [4]
    stats = memory.insert(*synthetic_batch(q.view(1, 1, 4)), torch.tensor([[100.0]]))
    assert stats.shifted == 1 and memory.returns[4] == 100.0 and memory.returns[5] == 0.0
    # The same inside an interacting group: a second transition within delta forces the sequential walk.
    memory.insert(*synthetic_batch(torch.stack([q - e, q + e]).unsqueeze(0) + 10), torch.zeros(1, 2))
    # t=1 at the centre (tie: slot 6) shifts slot 6 there with R=60; t=0, e/4 away, finds that key
    # first (slot 7 is within delta too, but farther) and shifts it again with R = 50 + 0.5 * 60.
    keys = torch.stack([q + 10 + e / 4, q + 10]).unsqueeze(0)
    stats = memory.insert(*synthetic_batch(keys), torch.tensor([[50.0, 60.0]]))
    assert stats == InsertStats(transitions=2, new=0, hits=2, shifted=2, evicted=0)
    assert torch.equal(memory.keys[6], q + 10 + e / 4) and memory.returns[6] == 80.0
    assert memory.returns[7] == 0.0


@pytest.mark.parametrize(
    ("track", "shape", "counter_reset"),
    [(False, "ball", False), (False, "box", False), (True, "ball", False), (True, "box", True)],
)
@pytest.mark.parametrize("spread", [0.0005, 0.003])
def test_batched_insert_equals_the_sequential_reference(
    track: bool, shape: str, counter_reset: bool, spread: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Clustered keys force many interactions inside each batch (shared entries, batch keys within delta,
    new entries hit later in the same batch), across several batches with eviction."""
    sequential = resolution._sequential
    walked: list[int] = []

    def counting(memory, group, *args, **kwargs):
        walked.append(group.numel())
        return sequential(memory, group, *args, **kwargs)

    monkeypatch.setattr(resolution, "_sequential", counting)
    generator = torch.Generator().manual_seed(int(spread * 1e4) + track)
    capacity, delta, gamma = 700, 0.004, 0.9
    memory = EpisodicMemory(
        KeyInState(),
        StateCodec(MAP10),
        capacity=capacity,
        tolerance=delta,
        gamma=gamma,
        track_desirability=track,
        check_states=False,  # synthetic states: keys written into the maps
        shape=shape,
        counter_reset=counter_reset,
    )
    ref = Reference(capacity, delta, gamma, MAP10.max_steps, track, shape=shape, counter_reset=counter_reset)
    batches: list = []
    interacting = 0
    for b in range(6):
        E, T = 6, 50
        keys = clustered_keys(E, T, clusters=40, spread=spread, generator=generator)
        state, counts = synthetic_batch(keys, seed=b)
        reward = torch.randint(-2, 3, (E, T), generator=generator).float()
        desirable = torch.rand(E, generator=generator) < 0.5 if track else None
        stats = run_both(memory, ref, state, counts, reward, desirable, batches)
        interacting += stats.hits
    assert ref.size == len(memory) and interacting > 300
    assert sum(walked) > 300  # many transitions interact
    if track:  # EMU's propagation chains the transitions of an episode: all are walked in order
        assert sum(walked) == 6 * 300
    elif spread > 0.001:
        assert sum(walked) < 6 * 300 * 0.75  # and many do not: both paths are exercised
    queries = torch.cat(
        [memory.keys[:300] + 0.001, clustered_keys(4, 50, 40, spread, generator).reshape(-1, 4)]
    )
    assert all(
        torch.equal(a, b)
        for a, b in zip(memory.lookup_keys(queries), brute_lookup(memory, queries), strict=True)
    )


def test_real_rollouts_with_a_neural_embedding_equal_the_reference() -> None:
    cfg = scenario("map10")
    memory = EpisodicMemory(
        TinyNet(cfg.state_dim), StateCodec(cfg), capacity=1000, tolerance=0.05, gamma=0.99
    )
    ref = Reference(1000, 0.05, 0.99, cfg.max_steps, False)
    batches: list = []
    states = []
    for seed in (5, 6, 5):  # the third batch repeats the first: its transitions find their keys
        state, counts, reward = rollout("map10", num_envs=8, seed=seed)
        states.append(state)
        stats = run_both(memory, ref, state, counts, reward, None, batches)
    assert stats.evicted > 0 and stats.hits > 200
    # Stored states decode exactly to the env's states they came from.
    slots = memory.live_slots()
    expected = torch.stack([states[b][e, t] for b, e, t in (ref.source[s] for s in slots.tolist())])
    assert torch.equal(memory.states(slots), expected)


def test_stored_states_decode_to_the_inserted_env_states() -> None:
    cfg = scenario("map15")
    state, counts, reward = rollout("map15", num_envs=4, seed=2)
    memory = EpisodicMemory(TinyNet(cfg.state_dim), StateCodec(cfg), capacity=2000, tolerance=1e-4)
    stats = memory.insert(state, counts, reward)
    assert stats.new == 4 * cfg.max_steps  # distinct states, tiny delta: all new
    slots = memory.live_slots()
    T = cfg.max_steps
    expected = state.flip(1).reshape(-1, cfg.state_dim)  # slot order = transition order
    assert torch.equal(memory.states(slots), expected)
    assert torch.equal(memory.step[slots].long(), torch.arange(T - 1, -1, -1).repeat(4))


# ------------------------------------------------------------------------------------------ eviction
def test_eviction_drops_the_oldest_entries_first() -> None:
    memory = EpisodicMemory(KeyInState(), StateCodec(MAP10), capacity=10, tolerance=1e-3, check_states=False)
    generator = torch.Generator().manual_seed(0)
    all_keys = []
    for b in range(3):
        keys = torch.randn(1, 4, 4, generator=generator) * 5
        all_keys.append(keys[0].flip(0))  # transition order
        stats = memory.insert(*synthetic_batch(keys, seed=b), torch.zeros(1, 4))
        assert stats.new == 4
    # 4 + 4 = 8; the third batch needs 4: 8 + 4 - 10 = 2 oldest go (the first two of batch 0).
    assert stats.evicted == 2 and len(memory) == 10
    expected = torch.cat(all_keys)[2:]
    assert torch.equal(memory.keys[memory.live_slots()], expected)
    assert memory.start == 2
    # Next batch of 4: 10 + 4 - 10 = 4 more evicted, new entries wrap around the ring.
    keys = torch.randn(1, 4, 4, generator=generator) * 5
    stats = memory.insert(*synthetic_batch(keys), torch.zeros(1, 4))
    assert stats.evicted == 4 and len(memory) == 10
    assert torch.equal(memory.keys[memory.live_slots()], torch.cat([expected[4:], keys[0].flip(0)]))
    assert memory.live_slots().tolist() == [6, 7, 8, 9, 0, 1, 2, 3, 4, 5]


def test_counts_of_another_step_are_refused() -> None:
    cfg = scenario("map10")
    memory = EpisodicMemory(TinyNet(cfg.state_dim), StateCodec(cfg), capacity=500)
    state, counts, reward = rollout("map10", num_envs=2, seed=0)
    with pytest.raises(ValueError, match="state maps are not the beliefs of counts"):
        memory.insert(state[:, 1:], counts[:, :-1], reward[:, 1:])  # s_{t+1} with the counts of s_t
    assert len(memory) == 0
    memory.insert(state, counts, reward)
    assert len(memory) == 100


def test_a_batch_larger_than_the_capacity_is_refused() -> None:
    memory = EpisodicMemory(KeyInState(), StateCodec(MAP10), capacity=3)
    with pytest.raises(ValueError, match="does not fit capacity=3"):
        memory.insert(*synthetic_batch(torch.randn(1, 4, 4)), torch.zeros(1, 4))


# ------------------------------------------------------------------------------------- look-ups
def test_lookups_match_brute_force_and_misses_are_zero() -> None:
    cfg = scenario("map10")
    memory = EpisodicMemory(TinyNet(cfg.state_dim), StateCodec(cfg), capacity=3000, tolerance=0.05)
    for seed in range(3):
        memory.insert(*rollout("map10", num_envs=8, seed=seed))
    state, _, _ = rollout("map10", num_envs=8, seed=1)
    time = memory.normalised_time(torch.arange(cfg.max_steps)).expand(8, -1)
    value, hit, slot = memory.lookup(state, time)
    assert value.shape == hit.shape == slot.shape == (8, cfg.max_steps)
    keys = memory.embedding(state, time).reshape(-1, 4).detach()
    expected = brute_lookup(memory, keys)
    assert torch.equal(value.reshape(-1), expected[0])
    assert torch.equal(hit.reshape(-1), expected[1])
    assert torch.equal(slot.reshape(-1), expected[2])
    far = keys + 100.0
    value, hit, slot = memory.lookup_keys(far)
    assert not hit.any() and value.eq(0).all() and slot.eq(-1).all()


def test_statistics_refresh_when_the_buffer_doubles() -> None:
    cfg = scenario("map10")
    memory = EpisodicMemory(TinyNet(cfg.state_dim), StateCodec(cfg), capacity=5000, tolerance=1e-4)
    sizes = []
    for seed in range(5):
        memory.insert(*rollout("map10", num_envs=4, seed=seed))
        sizes.append(memory.stats_size)
    assert sizes == [200, 400, 400, 800, 800]  # the first batch, then when the size reaches 400 and 800
    keys = memory.keys[memory.live_slots()].double()
    assert torch.allclose(memory.index.mean.double(), keys[:800].mean(0), atol=1e-6)


# ---------------------------------------------------------------------------------- re-embedding
def test_refresh_keys_re_embeds_every_state_and_lookups_follow() -> None:
    cfg = scenario("map10")
    embedding = TinyNet(cfg.state_dim, seed=0)
    memory = EpisodicMemory(embedding, StateCodec(cfg), capacity=900, tolerance=0.05)
    for seed in range(5):  # 1000 transitions into 900 slots: the ring has wrapped
        memory.insert(*rollout("map10", num_envs=4, seed=seed))
    old = memory.keys.clone()
    with torch.no_grad():
        for p, q in zip(embedding.parameters(), TinyNet(cfg.state_dim, seed=1).parameters(), strict=True):
            p.copy_(q)
    memory.refresh_keys(chunk=64)
    slots = memory.live_slots()
    with torch.no_grad():
        expected = embedding(memory.states(slots), memory.normalised_time(memory.step[slots]))
    assert torch.equal(memory.keys[slots], expected)
    assert not torch.equal(memory.keys[slots], old[slots])
    wide = expected.double()
    assert torch.allclose(memory.index.mean.double(), wide.mean(0), atol=1e-6)
    assert torch.allclose(memory.index.std.double(), wide.std(0, correction=0), rtol=1e-5)
    assert len(memory.index) == len(memory)  # rebuilt: no stale records
    queries = torch.cat([expected + 0.01, expected[:100]])
    assert all(
        torch.equal(a, b)
        for a, b in zip(memory.lookup_keys(queries), brute_lookup(memory, queries), strict=True)
    )


# -------------------------------------------------------------------------------------- promotion
def test_counts_above_255_promote_storage_and_keep_states_exact() -> None:
    tiny = scenario("map10", width=2, height=2, n_uavs=4, n_targets=1, n_no_fly=0, max_steps=300)
    state, counts, reward = (x[:, :] for x in _tiny_rollout(tiny))
    memory = EpisodicMemory(TinyNet(tiny.state_dim), StateCodec(tiny), capacity=1000, tolerance=1e-5)
    early = slice(0, 20)  # counts still small
    memory.insert(state[:, early], counts[:, early], reward[:, early])
    assert memory.codes.dtype == torch.uint8
    before = memory.states(memory.live_slots())
    memory.insert(state, counts, reward)
    assert counts.max() > 255 and memory.codes.dtype == torch.int16
    slots = memory.live_slots()
    assert torch.equal(memory.states(slots[:20]), before)  # old entries survive the promotion
    # The first 20 states are found again; the others are new entries, backwards in time.
    assert torch.equal(memory.states(slots[20:]), state[:, 20:].flip(1).reshape(-1, tiny.state_dim))


def _tiny_rollout(cfg):
    return env_rollout(cfg, 1, 0)


# ------------------------------------------------------------------------------------------- EMU
def test_emu_counters_on_a_hand_built_case() -> None:
    memory = hand_memory(track_desirability=True)
    keys = BASE.flip(0).unsqueeze(0)
    reward = torch.tensor([[0.0, 0.0, 0.0, 8.0]])  # R = (1, 2, 4, 8)
    memory.insert(*synthetic_batch(keys), reward, torch.tensor([False]))
    assert memory.n_call[:4].tolist() == [1, 1, 1, 1] and memory.n_xi[:4].tolist() == [0] * 4
    assert memory.xi[:4].tolist() == [False] * 4
    # Same keys, lower returns (R = 0.5, 1, 2, 4), a desirable episode: every entry is hit, and the
    # non-desirable entries shift to it (xi becomes True) although the returns are lower.
    reward = torch.tensor([[0.0, 0.0, 0.0, 4.0]])
    stats = memory.insert(*synthetic_batch(keys), reward, torch.tensor([True]))
    assert stats == InsertStats(transitions=4, new=0, hits=4, shifted=4, evicted=0)
    assert memory.n_call[:4].tolist() == [2, 2, 2, 2] and memory.n_xi[:4].tolist() == [1, 1, 1, 1]
    assert memory.xi[:4].tolist() == [True] * 4 and memory.returns[:4].tolist() == [4.0, 2.0, 1.0, 0.5]
    # A non-desirable episode with higher returns: normal shifts, xi stays True. Its last state (walked
    # first, slot 0) hits a desirable entry, so EMU's propagation makes its earlier states desirable:
    # N_xi grows on slots 1-3 only.
    reward = torch.tensor([[0.0, 0.0, 0.0, 16.0]])
    stats = memory.insert(*synthetic_batch(keys), reward, torch.tensor([False]))
    assert stats.shifted == 4 and memory.xi[:4].all() and memory.n_xi[:4].tolist() == [1, 2, 2, 2]
    assert memory.n_call[:4].tolist() == [3] * 4
    # A desirable episode with lower returns on desirable entries: hits only.
    stats = memory.insert(*synthetic_batch(keys), torch.zeros(1, 4), torch.tensor([True]))
    assert stats.shifted == 0 and memory.n_xi[:4].tolist() == [2, 3, 3, 3]
    ratio = memory.desirable_ratio(torch.tensor([0, 1, -1]))
    assert torch.allclose(ratio, torch.tensor([0.5, 0.75, 0.0]))
    # A new entry from a desirable episode starts with N_call = 1, N_xi = xi = 1.
    memory.insert(*synthetic_batch(BASE[:1].unsqueeze(0) + 5), torch.zeros(1, 1), torch.tensor([True]))
    assert memory.n_call[4] == 1 and memory.n_xi[4] == 1 and bool(memory.xi[4])
    # Propagation reaches new entries too: a non-desirable episode whose last state meets slot 4 (xi set)
    # writes its earlier, unseen state as desirable.
    keys = torch.stack([BASE[0] + 9, BASE[0] + 5]).unsqueeze(0)
    stats = memory.insert(*synthetic_batch(keys), torch.zeros(1, 2), torch.tensor([False]))
    assert stats == InsertStats(transitions=2, new=1, hits=1, shifted=0, evicted=0)
    assert memory.n_xi[4] == 1 and memory.n_call[4] == 2  # the hit itself was not desirable
    assert bool(memory.xi[5]) and memory.n_xi[5] == 1


@pytest.mark.parametrize("counter_reset", [False, True])
def test_emu_counter_reset_restarts_the_counters_on_a_desirability_shift(counter_reset: bool) -> None:
    memory = hand_memory(track_desirability=True, counter_reset=counter_reset)
    keys = BASE[:1].unsqueeze(0)
    for _ in range(3):  # three non-desirable visits: N_call = 3, N_xi = 0
        memory.insert(*synthetic_batch(keys), torch.ones(1, 1), torch.tensor([False]))
    assert memory.n_call[0] == 3 and memory.n_xi[0] == 0
    stats = memory.insert(*synthetic_batch(keys), torch.zeros(1, 1), torch.tensor([True]))
    assert stats.shifted == 1 and bool(memory.xi[0]) and memory.returns[0] == 0.0  # re-anchored, lower H
    expected = (1, 1) if counter_reset else (4, 1)  # EMU's flag_memory_cnt_reset, or the running counts
    assert (int(memory.n_call[0]), int(memory.n_xi[0])) == expected


def test_tracking_requires_the_desirable_flags() -> None:
    memory = hand_memory(track_desirability=True)
    with pytest.raises(ValueError, match=r"desirable must be a bool tensor of shape \[1\]"):
        memory.insert(*synthetic_batch(BASE.unsqueeze(0)), torch.zeros(1, 4))


# ---------------------------------------------------------------------------------------- sampling
def test_sample_draws_stored_states_with_their_time_and_return() -> None:
    cfg = scenario("map10")
    memory = EpisodicMemory(TinyNet(cfg.state_dim), StateCodec(cfg), capacity=500, tolerance=1e-4)
    memory.insert(*rollout("map10", num_envs=4, seed=0))
    state, time, returns = memory.sample(64, torch.Generator().manual_seed(0))
    assert state.shape == (64, cfg.state_dim) and time.shape == returns.shape == (64,)
    value, hit, _ = memory.lookup(state, time)
    assert hit.all() and torch.equal(value, returns)  # each sample finds itself
    again = memory.sample(64, torch.Generator().manual_seed(0))
    assert all(torch.equal(a, b) for a, b in zip((state, time, returns), again, strict=True))


# ------------------------------------------------------------------------------------- persistence
def test_state_dict_round_trip_answers_like_the_saved_memory(tmp_path) -> None:
    cfg = scenario("map10")
    embedding = TinyNet(cfg.state_dim)
    memory = EpisodicMemory(embedding, StateCodec(cfg), capacity=700, tolerance=0.05, track_desirability=True)
    for seed in range(4):  # wraps the ring
        memory.insert(*rollout("map10", num_envs=4, seed=seed), torch.tensor([True, False, True, False]))
    path = tmp_path / "memory.pt"
    torch.save(memory.state_dict(), path)
    state = torch.load(path, weights_only=True)
    loaded = EpisodicMemory(embedding, StateCodec(cfg), capacity=700, tolerance=0.05, track_desirability=True)
    loaded.load_state_dict(state)
    assert len(loaded) == len(memory) and loaded.start == memory.start
    assert torch.equal(loaded.live, memory.live)
    slots = memory.live_slots()
    for name in ("keys", "returns", "step", "codes", "positions", "n_call", "n_xi", "xi"):
        assert torch.equal(getattr(loaded, name)[slots], getattr(memory, name)[slots]), name
    assert torch.equal(loaded.index.mean, memory.index.mean) and torch.equal(
        loaded.index.std, memory.index.std
    )
    queries = torch.cat([memory.keys[slots] + 0.02, torch.randn(200, 4)])
    for a, b in zip(loaded.lookup_keys(queries), memory.lookup_keys(queries), strict=True):
        assert torch.equal(a, b)
    # A larger memory takes it too (slots laid out from 0; same answers).
    bigger = EpisodicMemory(
        embedding, StateCodec(cfg), capacity=2000, tolerance=0.05, track_desirability=True
    )
    bigger.load_state_dict(state)
    assert torch.equal(bigger.lookup_keys(queries)[0], memory.lookup_keys(queries)[0])


def test_state_dict_from_another_map_key_dim_or_too_large_is_refused() -> None:
    cfg = scenario("map10")
    memory = EpisodicMemory(TinyNet(cfg.state_dim), StateCodec(cfg), capacity=300, tolerance=0.05)
    memory.insert(*rollout("map10", num_envs=4, seed=0))
    state = memory.state_dict()
    other_map = scenario("map15")
    with pytest.raises(ValueError, match=r"another map.*width: saved 10, here 15"):
        EpisodicMemory(TinyNet(other_map.state_dim), StateCodec(other_map)).load_state_dict(state)
    with pytest.raises(ValueError, match="key_dim=4, this one has key_dim=3"):
        EpisodicMemory(TinyNet(cfg.state_dim, key_dim=3), StateCodec(cfg)).load_state_dict(state)
    with pytest.raises(ValueError, match="holds 200 entries, more than capacity=100"):
        EpisodicMemory(TinyNet(cfg.state_dim), StateCodec(cfg), capacity=100).load_state_dict(state)


def test_statistics_and_nbytes() -> None:
    cfg = scenario("map20")
    memory = EpisodicMemory(TinyNet(cfg.state_dim), StateCodec(cfg), capacity=1000)
    empty = memory.nbytes()
    assert empty >= 1000 * (cfg.n_cells * 2 + 40 * 2 + 16 + 4 + 2)
    stats = memory.statistics()
    assert stats["size"] == 0 and stats["capacity"] == 1000
    memory.insert(*rollout("map20", num_envs=2, seed=0))
    stats = memory.statistics()
    assert stats["size"] == 200 and stats["count_bytes"] == 1 and "return_mean" in stats
    assert memory.nbytes() > empty  # index records and the decode table


def test_stale_records_are_purged_and_lookups_stay_exact() -> None:
    """Many evictions and shifts: stale index records stay under stale_fraction of the entries."""
    cfg = scenario("map10")
    memory = EpisodicMemory(TinyNet(cfg.state_dim), StateCodec(cfg), capacity=500, tolerance=0.3)
    rebuilt = 0
    for seed in range(10):
        before = memory.stats_size, len(memory.index)
        stats = memory.insert(*rollout("map10", num_envs=4, seed=seed % 4))
        assert len(memory.index) - len(memory) <= 0.25 * len(memory)
        rebuilt += len(memory.index) < before[1] + stats.new
        queries = memory.keys[memory.live_slots()] + 0.05
        found = memory.lookup_keys(queries)
        assert all(torch.equal(a, b) for a, b in zip(found, brute_lookup(memory, queries), strict=True))
    assert rebuilt >= 2 and stats.shifted > 0 and stats.evicted > 0


def test_decoding_inside_inference_mode_leaves_reusable_buffers() -> None:
    cfg = scenario("map10")
    memory = EpisodicMemory(TinyNet(cfg.state_dim), StateCodec(cfg), capacity=300)
    state, counts, reward = rollout("map10", num_envs=2, seed=0)
    memory.insert(state, counts, reward)
    with torch.inference_mode():
        inside = memory.states(memory.live_slots())
    outside = memory.states(memory.live_slots())  # the codec's cached buffers are normal tensors
    assert torch.equal(inside, outside)
    assert torch.equal(outside, state.flip(1).reshape(-1, cfg.state_dim))


def test_inserting_under_inference_mode_leaves_a_usable_memory() -> None:
    tiny = scenario("map10", width=2, height=2, n_uavs=4, n_targets=1, n_no_fly=0, max_steps=300)
    state, counts, reward = _tiny_rollout(tiny)
    memory = EpisodicMemory(TinyNet(tiny.state_dim), StateCodec(tiny), capacity=1000, tolerance=1e-9)
    assert counts[:, 150:].max() > 255
    with torch.inference_mode():
        memory.insert(state[:, 150:], counts[:, 150:], reward[:, 150:])  # promotes to int16 in there
    memory.insert(state[:, :150], counts[:, :150], reward[:, :150])  # writes into what was allocated above
    assert memory.codes.dtype == torch.int16 and len(memory) > 250  # late states repeat (saturated maps)
    stored, inserted = memory.states(memory.live_slots()), state[0]
    assert (stored[:, None] == inserted[None]).all(-1).any(-1).all()  # every entry decodes to a real state
    memory.refresh_keys()
    assert memory.lookup_keys(memory.keys[memory.live_slots()])[1].all()
