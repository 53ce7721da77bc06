"""Exact nearest-neighbour-within-delta look-ups over the keys of D_E, batched and always current.

The reference code (EMC/EMU) queries a scipy KD-tree one transition at a time and rebuilds it every 200
episodes, so entries added in between are invisible. Only neighbours within ``delta`` matter, so a sorted
grid answers exactly for a whole batch, and new entries are visible at once without a rebuild.

Distances are taken on standardised float32 keys ``z = (x - mean) / std``. "Within delta" means, in the
index, the tests and the reference implementation alike::

    squared_distance(z_q, z_p) < float32(delta ** 2)      # shape="ball"
    max_i |z_q[i] - z_p[i]| <= float32(delta)             # shape="box", EMU's np.allclose(atol=delta)

In both shapes the nearest candidate has the smallest squared distance, the lowest slot on ties.

A record is a sort key, the slot and a copy of the slot's standardised key, in arrays sorted by the key
(:mod:`mcrs.memory.sorted_records`). The sort key ``(prefix << 32) + order(z[d-1])`` packs the cells
``floor(z[i] / side)`` of the first d - 1 dimensions (each modulo ``2^b``, ``b = 31 // (d - 1)``) and an
order-preserving integer of the last coordinate. So for each of the at most ``2^(d-1)`` cells met by ``[z -
reach, z + reach]`` a query reads one contiguous range, found by ``searchsorted``. New records go to a
small sorted array, merged into the main one past a sixteenth of its size.

Cells have side ``2 delta (1 + 2^-10)`` and queries reach ``delta (1 + 2^-11)``, at most two cells per
dimension, with the last coordinate's bounds rounded outwards; this is exact for ``|z| / delta < 1e10``.
The owner adds a record for every slot whose key it writes. Stale records stay until the next rebuild, but
a candidate counts only if its slot is live and holds the record's key. The statistics change only at a
refreshing rebuild or :meth:`GridIndex.set_statistics`; in between, a look-up equals the brute-force
nearest neighbour over the live keys."""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from typing import NamedTuple

import torch

from mcrs.choices import SHAPES
from mcrs.memory.sorted_records import (
    Records,
    flatnonzero,
    float_order,
    merge_records,
    repeat,
    search_sorted,
    slot_bits_for,
    unique_pairs,
)

MAX_KEY_DIM = 8  # 2^(d-1) cells per query
STD_FLOOR = 1e-6  # a dimension where every key is equal is not magnified beyond this
SIDE_MARGIN = 2.0**-10  # side = 2 delta (1 + SIDE_MARGIN)
REACH_MARGIN = 2.0**-11  # reach = delta (1 + REACH_MARGIN): 2 reach < side
MAX_CANDIDATES = 1 << 22  # candidates verified per chunk (bounds the temporary memory)
RECENT_SHARE = 16  # recent records are merged into the main ones beyond 1/16 of them ...
RECENT_MIN = 4096  # ... and this many (each merge copies every record: amortised over many insertions)
PREFIX_BITS = 31  # the prefix field of a sort key: (prefix << 32) + order < 2^63
NO_MATCH = torch.iinfo(torch.int64).max


def squared_distance(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """float32 squared Euclidean distance over the last dimension, summed dimension by dimension in order. The
    index, the memory and the tests all use this definition, so their results agree bit for bit; a library
    reduction may sum in another order."""
    diff = a - b
    sq = diff * diff
    out = sq[..., 0]
    for i in range(1, sq.shape[-1]):
        out = out + sq[..., i]
    return out


class QueryPlan(NamedTuple):
    """Per (query, cell) pair its ``query [R]``, and the sort-key bounds (R starts, R exclusive stops) sorted,
    with their ``order``."""

    query: torch.Tensor
    sorted: torch.Tensor
    order: torch.Tensor


class GridIndex:
    """The sorted grid over the slots of a key storage ``[capacity, key_dim]`` owned by the caller.

    Args:
        key_dim: dimension d of the keys, 1..8; a query searches up to 2^(d-1) cells.
        tolerance: delta on standardised keys: the ball's radius or the box's half-side.
        capacity: number of slots.
        device: where the records live, the keys' device.
        shape: ``"ball"`` or ``"box"``.
    """

    def __init__(
        self,
        key_dim: int,
        tolerance: float,
        capacity: int,
        device: torch.device | str = "cpu",
        shape: str = "ball",
    ) -> None:
        if isinstance(key_dim, bool) or not isinstance(key_dim, int) or not 1 <= key_dim <= MAX_KEY_DIM:
            raise ValueError(
                f"key_dim must be an int in [1, {MAX_KEY_DIM}] (2^(key_dim-1) cells per query), got {key_dim!r}"
            )
        if not (isinstance(tolerance, (int, float)) and 0 < tolerance < float("inf")):
            raise ValueError(f"tolerance must be a finite number > 0, got {tolerance!r}")
        if isinstance(capacity, bool) or not isinstance(capacity, int) or not 1 <= capacity < 2**31:
            raise ValueError(f"capacity must be an int in [1, 2^31), got {capacity!r}")
        if shape not in SHAPES:
            raise ValueError(f"shape must be one of {', '.join(SHAPES)}, got {shape!r}")
        self.key_dim, self.tolerance, self.capacity, self.shape = key_dim, float(tolerance), capacity, shape
        self.device = torch.device(device)
        self.side = 2.0 * self.tolerance * (1.0 + SIDE_MARGIN)
        self.reach = self.tolerance * (1.0 + REACH_MARGIN)
        self.tolerance_sq = torch.tensor(
            self.tolerance * self.tolerance, dtype=torch.float32, device=self.device
        )
        self.tolerance_f32 = torch.tensor(self.tolerance, dtype=torch.float32, device=self.device)
        self.slot_bits = slot_bits_for(capacity)
        self.prefix_bits = PREFIX_BITS // max(1, key_dim - 1)
        self._shifts = torch.arange(key_dim - 1, device=self.device, dtype=torch.int64) * self.prefix_bits
        self.mean = torch.zeros(key_dim, dtype=torch.float32, device=self.device)
        self.std = torch.ones(key_dim, dtype=torch.float32, device=self.device)
        self.records = self._empty(0)  # the main records
        self.recent = self._empty(0)  # records added since the last merge into the main ones
        self._buffers: list[Records | None] = [None, None]  # merge outputs, reused

    def _empty(self, n: int) -> Records:
        dev = self.device
        return Records(
            torch.empty(n, dtype=torch.int64, device=dev),
            torch.empty(n, dtype=torch.int32, device=dev),
            torch.empty(self.key_dim, n, device=dev),
        )

    # ------------------------------------------------------------------------------------ geometry
    def standardise(self, keys: torch.Tensor) -> torch.Tensor:
        """``(keys - mean) / std`` in float32: the space where delta applies."""
        return (keys.to(torch.float32) - self.mean) / self.std

    def set_statistics(self, keys: torch.Tensor) -> None:
        """Set per-dimension mean and population std (floor ``STD_FLOOR``) of ``keys [n, d]``; keep them if n
        == 0."""
        if keys.shape[0] == 0:
            return
        wide = keys.to(torch.float64)
        self.mean = wide.mean(0).to(torch.float32)
        self.std = wide.std(0, correction=0).clamp(min=STD_FLOOR).to(torch.float32)

    def sort_key(self, z: torch.Tensor) -> torch.Tensor:
        """The sort key ``[n]`` of standardised keys ``z [n, d]``: their cell's prefix, then the last coordinate."""
        cells = torch.floor(z[:, :-1].to(torch.float64) / self.side).to(torch.int64)
        return (self._pack(cells) << 32) + float_order(z[:, -1])

    def _pack(self, cells: torch.Tensor) -> torch.Tensor:
        mask = (1 << self.prefix_bits) - 1
        return ((cells & mask) << self._shifts).sum(-1)

    def query_cubes(self, z: torch.Tensor) -> QueryPlan:
        """Return the :class:`QueryPlan` of standardised queries ``z [M, d]``, reusable against any records.
        The cells met by ``[z - reach, z + reach]`` are built dimension by dimension: bit i of a cell's
        number picks the lower or the upper cell along dimension i."""
        M, d = z.shape
        wide = z.to(torch.float64)
        last = wide[:, -1]
        inf = torch.tensor(float("inf"), dtype=torch.float32, device=z.device)
        low_last = torch.nextafter((last - self.reach).to(torch.float32), -inf)  # rounded outwards
        high_last = torch.nextafter((last + self.reach).to(torch.float32), inf)
        prefix = torch.zeros(M, 1, dtype=torch.int64, device=z.device)
        valid = torch.ones(M, 1, dtype=torch.bool, device=z.device)
        if d > 1:
            low = torch.floor((wide[:, :-1] - self.reach) / self.side).to(torch.int64)
            two = torch.floor((wide[:, :-1] + self.reach) / self.side).to(torch.int64) > low  # [M, d-1]
            mask = (1 << self.prefix_bits) - 1
            lower = (low & mask) << self._shifts
            upper = ((low + 1) & mask) << self._shifts
            for i in range(d - 1):
                prefix = torch.cat([prefix + lower[:, i : i + 1], prefix + upper[:, i : i + 1]], 1)
                valid = torch.cat([valid, valid & two[:, i : i + 1]], 1)
        pair = flatnonzero(valid.view(-1))
        query = pair // prefix.shape[1]
        base = prefix.view(-1).index_select(0, pair) << 32
        bounds = torch.cat(
            [
                base + float_order(low_last).index_select(0, query),
                base + float_order(high_last).index_select(0, query) + 1,  # exclusive
            ]
        )
        ordered, order = torch.sort(bounds)
        return QueryPlan(query, ordered, order)

    # ------------------------------------------------------------------------------------ records
    def _records_of(self, z: torch.Tensor, slots: torch.Tensor, out: Records | None = None) -> Records:
        """Sorted records of standardised keys ``z [n, d]`` held by ``slots [n]``."""
        order, perm = torch.sort(self.sort_key(z))
        return Records(
            order, slots.to(torch.int32).index_select(0, perm), z.index_select(0, perm).t().contiguous()
        )

    def rebuild(self, keys: torch.Tensor, slots: torch.Tensor, refresh: bool = True) -> None:
        """Index exactly ``slots``, dropping every old record; ``refresh`` first recomputes the statistics
        over their keys."""
        current = keys[slots]
        if refresh:
            self.set_statistics(current)
        self.records = self._records_of(self.standardise(current), slots)
        self.recent = self.recent.prefix(0)
        self._buffers = [None, None]

    def clear(self) -> None:
        """Drop every record; the statistics stay."""
        self.records, self.recent = self.records.prefix(0), self.recent.prefix(0)

    def add(self, keys: torch.Tensor, slots: torch.Tensor) -> None:
        """Add records for ``slots`` with raw keys ``keys [n, d]``; the caller adds one for every slot whose
        key it writes."""
        if slots.numel() == 0:
            return
        self.recent = merge_records(self.recent, self._records_of(self.standardise(keys), slots))
        if self.recent.order.numel() > max(RECENT_MIN, self.records.order.numel() // RECENT_SHARE):
            self.flush()

    def flush(self) -> None:
        """Merge the recent records into the main ones now."""
        if self.recent.order.numel():
            total = len(self)
            self.records = merge_records(self.records, self.recent, self._spare(total))
            self.recent = self.recent.prefix(0)

    def _spare(self, size: int) -> Records:
        """Return whichever of the two reused merge buffers does not hold the current records."""
        holding = self.records.order.untyped_storage().data_ptr()
        for i, buffer in enumerate(self._buffers):
            if buffer is not None and buffer.order.untyped_storage().data_ptr() == holding:
                continue
            if buffer is None or buffer.order.numel() < size:
                buffer = self._buffers[i] = self._empty(size + size // 2 + 1024)
            return buffer
        raise AssertionError("unreachable: at most one buffer holds the records")

    def __len__(self) -> int:
        return self.records.order.numel() + self.recent.order.numel()

    def nbytes(self) -> int:
        """Bytes held by the records and the merge buffers."""
        arrays = [t for r in (*self._buffers, self.records, self.recent) if r is not None for t in r]
        return sum({t.untyped_storage().data_ptr(): t.untyped_storage().nbytes() for t in arrays}.values())

    # ------------------------------------------------------------------------------------ queries
    def nearest(
        self,
        z: torch.Tensor,
        keys: torch.Tensor,
        live: torch.Tensor,
        cubes: QueryPlan | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Return ``(slot [M] int64, squared distance [M] float32)`` of the nearest live slot within delta of
        each query, or ``(-1, inf)``.

        ``z [M, d]`` are standardised queries, ``keys [capacity, d]`` the current raw keys and ``live
        [capacity]`` the live slots. ``cubes`` may pass :meth:`query_cubes` of ``z``."""
        M = z.shape[0]
        best = torch.full((M,), NO_MATCH, dtype=torch.int64, device=z.device)
        cubes = self.query_cubes(z) if cubes is None else cubes
        for query, slot, d2 in self._candidates(z, cubes, keys, live):
            # Non-negative float32 bits order like the floats: (distance, slot) as one int64 to minimise.
            combined = (d2.view(torch.int32).to(torch.int64) << 32) | slot
            best.scatter_reduce_(0, query, combined, "amin")
        hit = best != NO_MATCH
        slot = torch.where(hit, best & 0xFFFFFFFF, -1)
        d2 = torch.where(hit, (best >> 32).to(torch.int32).view(torch.float32), float("inf"))
        return slot, d2

    def within(
        self,
        z: torch.Tensor,
        keys: torch.Tensor,
        live: torch.Tensor,
        cubes: QueryPlan | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Return every (query, live slot) pair within delta once, as ``(query [P], slot [P], d2 [P])`` sorted
        by query then slot."""
        cubes = self.query_cubes(z) if cubes is None else cubes
        parts = list(self._candidates(z, cubes, keys, live))
        return unique_pairs(parts, self.slot_bits, z.device)

    def pairs(
        self, z: torch.Tensor, cubes: QueryPlan | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Return every ordered pair ``(i, j)``, ``i != j``, of the points ``z [n, d]`` within delta of each
        other. The result ``(i [P], j [P], d2 [P])`` is sorted by i then j; it finds interacting
        transitions in a batch."""
        n = z.shape[0]
        records = self._records_of(z, torch.arange(n, device=z.device))
        parts = []
        for i, j, d2 in self._verified(z, records, cubes):
            other = i != j
            parts.append((i[other], j[other], d2[other]))
        return unique_pairs(parts, slot_bits_for(max(n, 2)), z.device)

    def _candidates(
        self, z: torch.Tensor, cubes: QueryPlan, keys: torch.Tensor, live: torch.Tensor
    ) -> Iterator[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
        """:meth:`_verified` over the main and the recent records."""
        for records in (self.records, self.recent):
            yield from self._verified(z, records, cubes, keys, live)

    def _verified(
        self,
        z: torch.Tensor,
        records: Records,
        cubes: QueryPlan | None = None,
        keys: torch.Tensor | None = None,
        live: torch.Tensor | None = None,
    ) -> Iterator[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
        """Yield, chunk by chunk, the candidates ``(query, slot, d2)`` within delta; duplicates are possible.
        With ``keys`` and ``live`` a candidate also needs a live slot whose current standardised key equals
        the record's copy, so stale records drop out."""
        if z.shape[0] == 0 or records.order.numel() == 0:
            return
        plan = self.query_cubes(z) if cubes is None else cubes
        found = search_sorted(records.order, plan.sorted)
        position = torch.empty_like(found)
        position[plan.order] = found
        R = plan.query.numel()
        low, counts = position[:R], position[R:] - position[:R]
        nonempty = flatnonzero(counts > 0)
        if nonempty.numel() == 0:
            return
        counts, low = counts.index_select(0, nonempty), low.index_select(0, nonempty)
        owner = plan.query.index_select(0, nonempty)
        # Chunks of ranges holding at most MAX_CANDIDATES candidates (one range may exceed it).
        cumulative = counts.cumsum(0)
        total = int(cumulative[-1])
        bounds = [0, counts.numel()]
        if total > MAX_CANDIDATES:
            cuts = torch.searchsorted(
                cumulative, torch.arange(MAX_CANDIDATES, total, MAX_CANDIDATES, device=z.device)
            )
            bounds = sorted(
                {0, counts.numel(), *(int(c) + 1 for c in cuts.tolist() if int(c) + 1 < counts.numel())}
            )
        columns = z.t().contiguous()  # [d, M]
        for start, stop in itertools.pairwise(bounds):
            c = counts[start:stop]
            n = int(c.sum())
            index = repeat(low[start:stop] - (c.cumsum(0) - c), c, n)
            index += torch.arange(n, device=z.device)  # consecutive records of each range
            query = repeat(owner[start:stop], c, n)
            query, index, d2 = self._inside(columns, query, records.coords, index)
            slot = records.slot.index_select(0, index)
            if keys is not None and live is not None:
                current = flatnonzero(live.index_select(0, slot))
                query, index, slot, d2 = (x.index_select(0, current) for x in (query, index, slot, d2))
                now = self.standardise(keys.index_select(0, slot)).t()
                same = flatnonzero((now == records.coords.index_select(1, index)).all(0))
                query, slot, d2 = (x.index_select(0, same) for x in (query, slot, d2))
            yield query, slot.to(torch.int64), d2

    def _inside(
        self, columns: torch.Tensor, query: torch.Tensor, coords: torch.Tensor, index: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Return the candidate pairs (query, record index) within delta and their squared distance.
        Dimensions are tested in order, summing as :func:`squared_distance` does; a pair leaves as soon as
        it fails the box or its partial sum reaches delta^2."""
        d2 = None
        for i in range(columns.shape[0]):
            diff = columns[i].index_select(0, query) - coords[i].index_select(0, index)
            if self.shape == "box":  # the distance only for the pairs that pass (below)
                keep = flatnonzero(diff.abs() <= self.tolerance_f32)
                query, index = query.index_select(0, keep), index.index_select(0, keep)
                continue
            d2 = diff * diff if d2 is None else d2 + diff * diff
            keep = flatnonzero(d2 < self.tolerance_sq)
            query, index, d2 = (x.index_select(0, keep) for x in (query, index, d2))
        if d2 is None:
            for i in range(columns.shape[0]):
                diff = columns[i].index_select(0, query) - coords[i].index_select(0, index)
                d2 = diff * diff if d2 is None else d2 + diff * diff
        return query, index, d2

    def matches(self, a: torch.Tensor, b: torch.Tensor, d2: torch.Tensor | None = None) -> torch.Tensor:
        """Whether standardised keys ``a`` and ``b`` ``[..., d]`` are within delta; ``d2`` may pass their
        squared distance."""
        if self.shape == "box":
            return (a - b).abs().amax(-1) <= self.tolerance_f32
        return (squared_distance(a, b) if d2 is None else d2) < self.tolerance_sq
