"""The grid index answers exactly like brute force on the current standardised keys."""

from __future__ import annotations

import pytest
import torch

import mcrs.memory.index as index_module
from mcrs.memory.index import GridIndex, squared_distance
from mcrs.memory.sorted_records import Records, float_order, merge_records

INF = float("inf")


@pytest.fixture(params=["recent", "merged"])
def upkeep(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Added records stay in the recent records (the default at these sizes), or are merged into the main
    ones at every addition: both layouts must answer alike."""
    if request.param == "merged":
        monkeypatch.setattr(index_module, "RECENT_MIN", 0)
        monkeypatch.setattr(index_module, "RECENT_SHARE", 1 << 40)
    return request.param


def brute_force(index: GridIndex, queries: torch.Tensor, keys: torch.Tensor, live: torch.Tensor):
    """Nearest live slot within delta (lowest slot on ties) and the full within-delta matrix."""
    z, stored = index.standardise(queries)[:, None, :], index.standardise(keys)[None, :, :]
    d2 = squared_distance(z, stored)
    if index.shape == "box":  # EMU: np.allclose(z, stored, rtol=0, atol=delta)
        within = ((z - stored).abs() <= torch.tensor(index.tolerance, dtype=torch.float32)).all(-1)
    else:
        within = d2 < torch.tensor(index.tolerance**2, dtype=torch.float32)
    within &= live[None, :]
    masked = torch.where(within, d2, torch.full_like(d2, INF))
    best, slot = masked.min(1)  # first minimum: the lowest slot
    return torch.where(torch.isfinite(best), slot, -1), within


def check(index: GridIndex, queries: torch.Tensor, keys: torch.Tensor, live: torch.Tensor) -> int:
    expected, within = brute_force(index, queries, keys, live)
    slot, d2 = index.nearest(index.standardise(queries), keys, live)
    assert torch.equal(slot, expected)
    hit = slot >= 0
    z = index.standardise(queries)
    assert torch.equal(d2[hit], squared_distance(z[hit], index.standardise(keys[slot[hit]])))
    assert torch.isinf(d2[~hit]).all()
    q, s, _ = index.within(z, keys, live)
    found = torch.zeros_like(within)
    found[q, s] = True
    assert torch.equal(found, within) and q.numel() == int(within.sum())  # each pair exactly once
    return int(hit.sum())


@pytest.mark.parametrize("shape", ["ball", "box"])
@pytest.mark.parametrize("key_dim", [1, 2, 4, 8])
def test_random_queries_match_brute_force(key_dim: int, shape: str) -> None:
    generator = torch.Generator().manual_seed(key_dim)
    capacity, delta = 4000, 0.08
    keys = torch.randn(capacity, key_dim, generator=generator) * 3 + 1
    live = torch.rand(capacity, generator=generator) < 0.7
    index = GridIndex(key_dim, delta, capacity, shape=shape)
    index.rebuild(keys, live.nonzero().squeeze(1))
    assert torch.allclose(index.mean, keys[live].mean(0), atol=1e-5)
    assert torch.allclose(index.std, keys[live].std(0, correction=0), rtol=1e-5)
    near = keys[:1500] + torch.randn(1500, key_dim, generator=generator) * index.std * delta * 0.4
    queries = torch.cat([near, keys[1500:1700], torch.randn(500, key_dim, generator=generator) * 3])
    hits = check(index, queries, keys, live)
    assert 500 < hits < queries.shape[0]  # both outcomes occur


@pytest.mark.parametrize("shape", ["ball", "box"])
@pytest.mark.parametrize("key_dim", [2, 4])
def test_points_on_cube_borders_and_at_distance_delta(key_dim: int, shape: str) -> None:
    """Keys exactly on cube borders, queries a hair inside and outside delta along every axis, duplicates."""
    delta = 0.01
    index = GridIndex(key_dim, delta, 4096, shape=shape)
    side = index.side
    lattice = torch.arange(-3, 4, dtype=torch.float64) * side
    grid = torch.stack(torch.meshgrid(*[lattice] * key_dim, indexing="ij"), -1).reshape(-1, key_dim)
    grid = grid[torch.randperm(grid.shape[0], generator=torch.Generator().manual_seed(0))[:1000]]
    n = grid.shape[0]
    keys = torch.cat([grid, grid[:20]]).to(torch.float32)  # duplicates: the lowest slot wins
    live = torch.ones(keys.shape[0], dtype=torch.bool)
    index.mean, index.std = torch.zeros(key_dim), torch.ones(key_dim)  # standardised == raw
    index.rebuild(keys, torch.arange(keys.shape[0]), refresh=False)
    queries = []
    for step in (delta, delta * (1 - 1e-7), delta * (1 + 1e-7), delta / 2, side / 2, side - delta):
        for axis in range(key_dim):
            for sign in (1.0, -1.0):
                offset = torch.zeros(key_dim, dtype=torch.float64)
                offset[axis] = sign * step
                queries.append(grid[:40] + offset)
    queries.append(grid[:40] + torch.full((key_dim,), delta / key_dim**0.5, dtype=torch.float64))
    queries.append(grid[:40] + torch.full((key_dim,), delta * 0.99, dtype=torch.float64))  # a box corner
    queries = torch.cat(queries).to(torch.float32)
    # Also nudge queries bit by bit across the strict boundary d^2 = float32(delta^2).
    base = keys[:20].clone()
    nudged = []
    for axis in {0, key_dim - 1}:  # a prefix dimension, and the last one (searched by exact range)
        for sign in (1.0, -1.0):
            edge = base.clone()
            edge[:, axis] += torch.tensor(sign * delta, dtype=torch.float32)
            nudged.append(edge)
            for _ in range(3):
                nudged.append(torch.nextafter(nudged[-1], torch.full_like(edge, INF)))
            for _ in range(3):
                nudged.append(torch.nextafter(nudged[-4 if _ == 0 else -1], torch.full_like(edge, -INF)))
    queries = torch.cat([queries, *nudged, keys])
    hits = check(index, queries, keys, live)
    assert 0 < hits < queries.shape[0]
    slot, _ = index.nearest(index.standardise(keys[n:]), keys, live)
    assert torch.equal(slot, torch.arange(20))  # a key and its duplicate: the lowest slot


@pytest.mark.parametrize("shape", ["ball", "box"])
def test_stale_records_and_dead_slots_are_harmless(shape: str, upkeep: str) -> None:
    """Moving keys (shifts) and killing slots (evictions) with records left behind changes nothing."""
    generator = torch.Generator().manual_seed(2)
    capacity, delta = 3000, 0.1
    keys = torch.randn(capacity, 4, generator=generator)
    live = torch.ones(capacity, dtype=torch.bool)
    index = GridIndex(4, delta, capacity, shape=shape)
    index.rebuild(keys, torch.arange(capacity))
    before = keys.clone()
    # Shift 500 slots onto other places and add their new records; the old ones stay, stale.
    moved = torch.randperm(capacity, generator=generator)[:500]
    keys[moved] = keys[torch.randint(0, capacity, (500,), generator=generator)] + 0.01
    index.add(keys[moved], moved)
    # Evict 300 slots (records stay), then reuse 100 of them with new keys.
    dead = torch.randperm(capacity, generator=generator)[:300]
    live[dead] = False
    reused = dead[:100]
    keys[reused] = torch.randn(100, 4, generator=generator)
    live[reused] = True
    index.add(keys[reused], reused)
    # Nudge 200 keys within their cell (same prefix, the copy in the old record no longer matches).
    nudged = torch.randperm(capacity, generator=generator)[:200]
    keys[nudged] += 1e-4
    index.add(keys[nudged], nudged)
    assert len(index) == capacity + 800
    changed = torch.cat([moved, dead, nudged, torch.arange(300)])  # and 300 untouched slots
    queries = torch.cat([before[changed], keys[changed], keys[moved] + 0.005, before[nudged] - 0.9 * delta])
    check(index, queries, keys, live)
    index.flush()  # the recent records merged into the main ones: the same answers
    assert len(index.recent.order) == 0 and len(index) == capacity + 800
    check(index, queries, keys, live)


def test_added_records_are_visible_at_once(upkeep: str) -> None:
    keys = torch.zeros(100, 4)
    live = torch.zeros(100, dtype=torch.bool)
    index = GridIndex(4, 0.05, 100)
    generator = torch.Generator().manual_seed(3)
    for start in range(0, 100, 10):
        slots = torch.arange(start, start + 10)
        keys[slots] = torch.randn(10, 4, generator=generator)
        live[slots] = True
        index.add(keys[slots], slots)
        check(index, keys, keys, live)
        slot, _ = index.nearest(index.standardise(keys[: start + 10]), keys, live)
        assert torch.equal(slot, torch.arange(start + 10))


def test_pairs_within_a_batch_match_brute_force() -> None:
    generator = torch.Generator().manual_seed(4)
    index = GridIndex(4, 0.05, 1000)
    centres = torch.randn(30, 4, generator=generator)
    z = (
        centres[torch.randint(0, 30, (600,), generator=generator)]
        + torch.randn(600, 4, generator=generator) * 0.02
    )
    z = torch.cat([z, z[:10]])  # exact duplicates
    i, j, d2 = index.pairs(z)
    dist = squared_distance(z[:, None], z[None])
    expected = (dist < index.tolerance_sq) & ~torch.eye(z.shape[0], dtype=torch.bool)
    found = torch.zeros_like(expected)
    found[i, j] = True
    assert torch.equal(found, expected) and i.numel() == int(expected.sum())
    assert torch.equal(d2, dist[i, j])
    assert (i[1:] > i[:-1]).logical_or((i[1:] == i[:-1]) & (j[1:] > j[:-1])).all()  # sorted by (i, j)


def test_many_candidates_are_processed_in_chunks(monkeypatch: pytest.MonkeyPatch) -> None:
    import mcrs.memory.index as module

    monkeypatch.setattr(module, "MAX_CANDIDATES", 50)
    keys = torch.randn(400, 2, generator=torch.Generator().manual_seed(5)) * 0.01  # dense: many per cube
    live = torch.ones(400, dtype=torch.bool)
    index = GridIndex(2, 0.5, 400)
    index.mean, index.std = torch.zeros(2), torch.ones(2)
    index.rebuild(keys, torch.arange(400), refresh=False)
    check(index, keys[:100] + 0.001, keys, live)


def test_negative_zero_and_the_order_of_floats() -> None:
    """The last coordinate is searched through its float32 bits: -0.0 and 0.0 are one value, and the order
    of the bits is the order of the floats (negative, denormal, infinite included)."""
    values = torch.tensor([-INF, -3.0, -1e-40, -0.0, 0.0, 1e-40, 2.5, INF])
    order = float_order(values)
    assert order[3] == order[4] and (order[1:4] > order[:3]).all() and (order[5:] > order[4:-1]).all()
    keys = torch.tensor([[0.0, -0.0], [0.0, 0.0], [0.0, 0.05]])
    live = torch.ones(3, dtype=torch.bool)
    for shape in ("ball", "box"):
        index = GridIndex(2, 0.05, 3, shape=shape)
        index.mean, index.std = torch.zeros(2), torch.ones(2)
        index.rebuild(keys, torch.arange(3), refresh=False)
        queries = torch.tensor([[0.0, 0.0], [0.0, -0.0], [0.0, -0.05], [0.0, 0.1], [0.01, 0.04]])
        check(index, queries, keys, live)


def test_merge_records_equals_sorting_the_union() -> None:
    """Merged records are the union sorted by key, each record's slot and copy carried with it."""
    generator = torch.Generator().manual_seed(6)

    def records(n: int) -> Records:
        order = torch.randint(0, 1000, (n,), generator=generator).sort().values
        slot = torch.randint(0, 1 << 30, (n,), generator=generator, dtype=torch.int32)
        return Records(order, slot, torch.stack([order.float() * 2, slot.float()]))

    a, b = records(5000), records(300)
    merged = merge_records(a, b)
    assert torch.equal(merged.order, torch.cat([a.order, b.order]).sort().values)
    assert torch.equal(merged.coords[0], merged.order.float() * 2)  # the rows travel together
    assert torch.equal(merged.coords[1], merged.slot.float())
    pairs = sorted(
        zip(torch.cat([a.order, b.order]).tolist(), torch.cat([a.slot, b.slot]).tolist(), strict=True)
    )
    assert sorted(zip(merged.order.tolist(), merged.slot.tolist(), strict=True)) == pairs
    assert torch.equal(merge_records(a, b.prefix(0)).order, a.order)
    assert torch.equal(merge_records(a.prefix(0), b).slot, b.slot)


def test_constant_dimension_gets_a_floor_not_a_division_by_zero() -> None:
    keys = torch.zeros(50, 4)
    keys[:, 0] = torch.arange(50.0)
    index = GridIndex(4, 0.01, 50)
    index.rebuild(keys, torch.arange(50))
    assert torch.isfinite(index.standardise(keys)).all()
    assert index.std[1:].eq(1e-6).all()


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"key_dim": 0}, "key_dim must be an int in"),
        ({"key_dim": 9}, "key_dim must be an int in"),
        ({"tolerance": 0.0}, "tolerance must be a finite number > 0"),
        ({"tolerance": float("inf")}, "tolerance must be a finite number > 0"),
        ({"capacity": 0}, "capacity must be an int"),
    ],
)
def test_bad_arguments_are_refused(kwargs: dict, message: str) -> None:
    args = {"key_dim": 4, "tolerance": 0.1, "capacity": 10, **kwargs}
    with pytest.raises(ValueError, match=message):
        GridIndex(**args)


def test_box_and_ball_differ_exactly_where_their_shapes_do() -> None:
    """A key at a box corner (every coordinate 0.9 delta away) is in EMU's box, outside the ball; a key one
    delta-hair away along one axis is in both; a key 1.1 delta away along one axis is in neither."""
    delta, key_dim = 0.1, 4
    keys = torch.tensor([[0.0] * 4, [9.0] * 4])
    live = torch.ones(2, dtype=torch.bool)
    corner = torch.full((1, key_dim), 0.9 * delta)
    axis = torch.tensor([[0.99 * delta, 0, 0, 0]])
    outside = torch.tensor([[1.1 * delta, 0, 0, 0]])
    queries = torch.cat([corner, axis, outside])
    found = {}
    for shape in ("ball", "box"):
        index = GridIndex(key_dim, delta, 2, shape=shape)
        index.mean, index.std = torch.zeros(key_dim), torch.ones(key_dim)
        index.rebuild(keys, torch.arange(2), refresh=False)
        found[shape] = index.nearest(queries, keys, live)[0].tolist()
        check(index, queries, keys, live)
    assert found == {"ball": [-1, 0, -1], "box": [0, 0, -1]}


def test_an_unknown_shape_is_refused_naming_the_choices() -> None:
    with pytest.raises(ValueError, match=r"shape must be one of ball, box, got 'cube'"):
        GridIndex(4, 0.1, 10, shape="cube")
