"""Exact nearest-neighbour-within-delta look-ups over the keys of D_E, batched and always current.

Why not a KD-tree: the reference code (EMC/EMU) queries a scipy tree one transition at a time and rebuilds
it every 200 episodes, so entries added in between are invisible. Only neighbours closer than ``delta``
matter, and delta is tiny (1.3e-3 in standardised units), so a grid hash answers exactly with a handful of
sorted-array searches per query, for a whole batch at once, and new entries are visible immediately.

**Geometry.** Distances are taken on *standardised* keys ``z = (x - mean) / std`` (float32, per dimension,
statistics over the buffer; see "Statistics" below). "Within delta" means, exactly and everywhere (index,
tests, reference implementation)::

    squared_distance(z_q, z_p) < float32(delta ** 2)

with :func:`squared_distance` summing the float32 squared differences dimension by dimension in order
(``shape="ball"``), or, with ``shape="box"`` (EMU's ``np.allclose(..., rtol=0, atol=delta)``)::

    max_i |z_q[i] - z_p[i]| <= float32(delta)

In both shapes the nearest candidate is the one of smallest squared distance (lowest slot on ties).

**Grid.** Space is cut into cubes of side ``2 delta (1 + 2^-10)``; a key lives in the cube
``floor(z / side)`` (computed in float64 from the float32 z). A point within delta of a query differs from
it by less than ``delta (1 + 2^-11)`` in every dimension (in either shape) (float32 subtraction is correctly rounded, so the
computed distance bounds the true difference up to a relative 2^-22), so it lies in one of the cubes met by
``[z - reach, z + reach]`` per dimension, ``reach = delta (1 + 2^-11)``: since ``2 reach < side``, at most
two per dimension, ``2^d`` cubes in all (d = 4: 16). The float64 cube arithmetic is exact enough for
``|z| / delta < 1e10``.

**Records.** Each record is one int64: ``(cube hash << slot_bits) | slot``, in one sorted array; a cube's
records are one contiguous range found with two ``searchsorted``. The cube hash packs each cube coordinate
modulo ``2^b`` (``b = (62 - slot_bits) // d``); distinct cubes that share a hash only add candidates.
Every candidate is verified against the *current* key of its slot and the slot's liveness, so records left
behind by a memory shift (the slot moved to another cube) or an eviction (the slot is dead or reused) are
harmless: they cost a little time until the next rebuild purges them. New records are merged into the
sorted array in O(records) (a memcpy-like merge, not a sort). Most of a query's 2^d cubes are empty, so
an occupancy table (one byte per bucket of a mixed cube hash, about 16 buckets per slot) is checked first:
only cubes whose bucket is occupied are searched. It is a superset filter (set for every record, cleared
only at a rebuild), so it never hides a record.

**Statistics.** ``mean`` and ``std`` change only when the index is rebuilt (:meth:`GridIndex.rebuild` with
``refresh=True``) or set explicitly (:meth:`GridIndex.set_statistics`); the owner
(:class:`~mcrs.memory.episodic.EpisodicMemory`) documents when that happens. Between two refreshes every
key is hashed with the same statistics, so a look-up always equals the brute-force nearest neighbour over
the current live keys standardised with the current statistics (ties: lowest slot).
"""

from __future__ import annotations

import itertools

import numpy as np
import torch

MAX_KEY_DIM = 8  # 2^d cubes per query
STD_FLOOR = 1e-6  # a dimension where every key is equal is not magnified beyond this
SIDE_MARGIN = 2.0**-10  # side = 2 delta (1 + SIDE_MARGIN)
REACH_MARGIN = 2.0**-11  # reach = delta (1 + REACH_MARGIN): 2 reach < side
MAX_CANDIDATES = 1 << 22  # candidates verified per chunk (bounds the temporary memory)
MAX_OCCUPANCY_BITS = 26  # at most 64 MiB of occupancy table
NO_MATCH = torch.iinfo(torch.int64).max
SHAPES = ("ball", "box")  # Euclidean ball of radius delta | EMU's per-dimension box of half-side delta


def squared_distance(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """float32 squared Euclidean distance over the last dimension, summed dimension by dimension in order.

    The one definition of the distance used by the index, the memory and the tests, so that results are
    bit-for-bit comparable (a library reduction may sum in another order).
    """
    diff = a - b
    sq = diff * diff
    out = sq[..., 0]
    for i in range(1, sq.shape[-1]):
        out = out + sq[..., i]
    return out


def slot_bits_for(capacity: int) -> int:
    """Bits that hold a slot number below ``capacity``."""
    return max(1, (capacity - 1).bit_length())


def occupancy_bits_for(capacity: int) -> int:
    """Buckets (log2) of the occupancy table: about 16 per slot, so that few empty cubes look occupied."""
    return min(MAX_OCCUPANCY_BITS, max(10, (16 * capacity - 1).bit_length()))


def bucket(hashes: torch.Tensor, bits: int) -> torch.Tensor:
    """Mix cube hashes (< 2^62) into ``[0, 2^bits)``; every step stays below 2^63 (no overflow)."""
    folded = (hashes ^ (hashes >> 21) ^ (hashes >> 42)) & 0x7FFFFFFF
    return ((folded * 0x5BD1E995) & 0x7FFFFFFF) >> (31 - bits)


def occupancy(hashes: torch.Tensor, bits: int) -> torch.Tensor:
    """A table ``[2^bits]`` bool marking the buckets of ``hashes``."""
    table = torch.zeros(1 << bits, dtype=torch.bool, device=hashes.device)
    table[bucket(hashes, bits)] = True
    return table


def merge_sorted(a: torch.Tensor, b: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
    """Merge two sorted int64 arrays in O(len(a) + len(b)) (``a`` large, ``b`` small): a copy, not a sort.

    ``out`` (at least ``len(a) + len(b)`` long, not overlapping ``a``) may provide the memory; the result
    is its prefix.
    """
    if b.numel() == 0:
        return a
    total = a.numel() + b.numel()
    out = torch.empty(total, dtype=a.dtype, device=a.device) if out is None else out[:total]
    keep = torch.ones(total, dtype=torch.bool, device=a.device)
    if a.device.type == "cpu":
        # numpy's boolean-mask copy is one pass; torch's CPU masked copies are ~20x slower.
        a_np, b_np, out_np, keep_np = a.numpy(), b.numpy(), out.numpy(), keep.numpy()
        position = np.searchsorted(a_np, b_np, side="right") + np.arange(b_np.size)
        keep_np[position] = False
        out_np[keep_np] = a_np
        out_np[position] = b_np
        return out
    position = torch.searchsorted(a, b, right=True) + torch.arange(b.numel(), device=a.device)
    keep[position] = False
    out[keep] = a
    out[position] = b
    return out


class GridIndex:
    """The grid hash over the slots of a key storage ``[capacity, key_dim]`` owned by the caller.

    Args:
        key_dim: dimension d of the keys (1..8; a query checks 2^d cubes).
        delta: the match tolerance on standardised keys (> 0): the ball's radius or the box's half-side.
        capacity: number of slots (record values carry the slot number).
        device: where the records live (the keys' device).
        shape: ``"ball"`` or ``"box"`` (see the module docstring).
    """

    def __init__(
        self,
        key_dim: int,
        delta: float,
        capacity: int,
        device: torch.device | str = "cpu",
        shape: str = "ball",
    ) -> None:
        if isinstance(key_dim, bool) or not isinstance(key_dim, int) or not 1 <= key_dim <= MAX_KEY_DIM:
            raise ValueError(
                f"key_dim must be an int in [1, {MAX_KEY_DIM}] (2^key_dim cubes per query), got {key_dim!r}"
            )
        if not (isinstance(delta, (int, float)) and 0 < delta < float("inf")):
            raise ValueError(f"delta must be a finite number > 0, got {delta!r}")
        if isinstance(capacity, bool) or not isinstance(capacity, int) or not 1 <= capacity < 2**31:
            raise ValueError(f"capacity must be an int in [1, 2^31), got {capacity!r}")
        if shape not in SHAPES:
            raise ValueError(f"shape must be one of {', '.join(SHAPES)}, got {shape!r}")
        self.key_dim, self.delta, self.capacity, self.shape = key_dim, float(delta), capacity, shape
        self.device = torch.device(device)
        self.side = 2.0 * self.delta * (1.0 + SIDE_MARGIN)
        self.reach = self.delta * (1.0 + REACH_MARGIN)
        self.delta_sq = torch.tensor(self.delta * self.delta, dtype=torch.float32, device=self.device)
        self.delta_f32 = torch.tensor(self.delta, dtype=torch.float32, device=self.device)
        self.slot_bits = slot_bits_for(capacity)
        # (hash + 1) << slot_bits must stay below 2^63: the hash has at most 62 - slot_bits bits.
        self.hash_bits = (62 - self.slot_bits) // key_dim
        if self.hash_bits < 1:
            raise ValueError(f"capacity {capacity} leaves no hash bits for key_dim {key_dim}")
        self.mean = torch.zeros(key_dim, dtype=torch.float32, device=self.device)
        self.std = torch.ones(key_dim, dtype=torch.float32, device=self.device)
        self.records = torch.zeros(0, dtype=torch.int64, device=self.device)
        self._buffers: list[torch.Tensor | None] = [None, None]  # merge outputs, reused
        self.occupancy_bits = occupancy_bits_for(capacity)
        self.occupied = torch.zeros(1 << self.occupancy_bits, dtype=torch.bool, device=self.device)
        self._shifts = torch.arange(key_dim, device=self.device, dtype=torch.int64) * self.hash_bits

    # ------------------------------------------------------------------------------------ geometry
    def standardise(self, keys: torch.Tensor) -> torch.Tensor:
        """``(keys - mean) / std`` in float32: the space where delta applies."""
        return (keys.to(torch.float32) - self.mean) / self.std

    def set_statistics(self, keys: torch.Tensor) -> None:
        """Per-dimension mean and std (population, floor ``STD_FLOOR``) of ``keys [n, d]``; kept if n == 0."""
        if keys.shape[0] == 0:
            return
        wide = keys.to(torch.float64)
        self.mean = wide.mean(0).to(torch.float32)
        self.std = wide.std(0, correction=0).clamp(min=STD_FLOOR).to(torch.float32)

    def cube_hash(self, z: torch.Tensor) -> torch.Tensor:
        """Hash ``[...]`` of the cube holding each standardised key ``z [..., d]``."""
        return self._pack(torch.floor(z.to(torch.float64) / self.side).to(torch.int64))

    def _pack(self, cube: torch.Tensor) -> torch.Tensor:
        mask = (1 << self.hash_bits) - 1
        return ((cube & mask) << self._shifts).sum(-1)

    def query_cubes(self, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Hashes ``[M, 2^d]`` of the cubes met by ``[z - reach, z + reach]``, and which of them are distinct.

        Cube c (bit i of c: the lower or the upper cube along dimension i) is built dimension by
        dimension: the hash is a sum of per-dimension bit fields.
        """
        wide = z.to(torch.float64)
        low = torch.floor((wide - self.reach) / self.side).to(torch.int64)
        two = torch.floor((wide + self.reach) / self.side).to(torch.int64) > low  # [M, d]
        mask = (1 << self.hash_bits) - 1
        lower = (low & mask) << self._shifts
        upper = ((low + 1) & mask) << self._shifts
        hashes = torch.zeros(z.shape[0], 1, dtype=torch.int64, device=z.device)
        valid = torch.ones(z.shape[0], 1, dtype=torch.bool, device=z.device)
        for i in range(self.key_dim):
            hashes = torch.cat([hashes + lower[:, i : i + 1], hashes + upper[:, i : i + 1]], 1)
            valid = torch.cat([valid, valid & two[:, i : i + 1]], 1)
        return hashes, valid

    # ------------------------------------------------------------------------------------ records
    def rebuild(self, keys: torch.Tensor, slots: torch.Tensor, refresh: bool = True) -> None:
        """Index exactly ``slots`` (their keys ``keys[slots]``), dropping every old record.

        With ``refresh`` the statistics are first recomputed over those keys.
        """
        current = keys[slots]
        if refresh:
            self.set_statistics(current)
        cubes = self.cube_hash(self.standardise(current))
        self.records = torch.sort((cubes << self.slot_bits) | slots.to(torch.int64)).values
        self.occupied.zero_()
        self.occupied[bucket(cubes, self.occupancy_bits)] = True

    def clear(self) -> None:
        """Drop every record (the statistics stay)."""
        self.records = self.records[:0]
        self.occupied.zero_()

    def add(self, keys: torch.Tensor, slots: torch.Tensor) -> None:
        """Add records for ``slots`` whose keys are ``keys [n, d]`` (raw, not standardised)."""
        if slots.numel():
            cubes = self.cube_hash(self.standardise(keys))
            new = torch.sort((cubes << self.slot_bits) | slots.to(torch.int64)).values
            self.records = merge_sorted(self.records, new, out=self._spare(len(self) + new.numel()))
            self.occupied[bucket(cubes, self.occupancy_bits)] = True

    def _spare(self, size: int) -> torch.Tensor:
        """The merge buffer (of two, reused: no fresh pages per insert) not holding the current records."""
        holding = self.records.untyped_storage().data_ptr()
        for i, buffer in enumerate(self._buffers):
            if buffer is not None and buffer.untyped_storage().data_ptr() == holding:
                continue
            if buffer is None or buffer.numel() < size:
                buffer = self._buffers[i] = torch.empty(
                    size + size // 2 + 1024, dtype=torch.int64, device=self.device
                )
            return buffer
        raise AssertionError("unreachable: at most one buffer holds the records")

    def __len__(self) -> int:
        return self.records.numel()

    def nbytes(self) -> int:
        held = {
            b.untyped_storage().data_ptr(): b.untyped_storage().nbytes()
            for b in self._buffers
            if b is not None
        }
        held[self.records.untyped_storage().data_ptr()] = self.records.untyped_storage().nbytes()
        return sum(held.values()) + self.occupied.numel()

    # ------------------------------------------------------------------------------------ queries
    def nearest(
        self,
        z: torch.Tensor,
        keys: torch.Tensor,
        live: torch.Tensor,
        cubes: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """For standardised queries ``z [M, d]``: ``(slot [M] int64, squared distance [M] float32)`` of the
        nearest live slot within delta (lowest slot on ties), or ``(-1, inf)``.

        ``keys [capacity, d]`` are the current raw keys, ``live [capacity]`` bool marks the live slots;
        ``cubes`` may pass :meth:`query_cubes` of ``z`` when already computed.
        """
        M = z.shape[0]
        best = torch.full((M,), NO_MATCH, dtype=torch.int64, device=z.device)
        for query, slot, d2 in self._verified(
            z, self.records, self.slot_bits, self.occupied, keys, live, cubes
        ):
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
        cubes: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Every (query, live slot) pair within delta, each once: ``(query [P], slot [P], d2 [P])``,
        sorted by query then slot."""
        parts = list(self._verified(z, self.records, self.slot_bits, self.occupied, keys, live, cubes))
        if not parts:
            empty = torch.zeros(0, dtype=torch.int64, device=z.device)
            return empty, empty, torch.zeros(0, dtype=torch.float32, device=z.device)
        query, slot, d2 = (torch.cat(x) for x in zip(*parts, strict=True))
        # A slot can be found twice (a stale record and a current one): keep one of each pair.
        pair, order = torch.sort((query << self.slot_bits) | slot)
        first = torch.ones_like(pair, dtype=torch.bool)
        first[1:] = pair[1:] != pair[:-1]
        order = order[first]
        return query[order], slot[order], d2[order]

    def pairs(
        self, z: torch.Tensor, cubes: tuple[torch.Tensor, torch.Tensor] | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Every ordered pair ``(i, j)``, ``i != j``, of the points ``z [n, d]`` within delta of each other:
        ``(i [P], j [P], d2 [P])`` sorted by i then j (used to find interacting transitions in a batch)."""
        n = z.shape[0]
        bits = slot_bits_for(max(n, 2))
        own = self.cube_hash(z)
        records = torch.sort((own << bits) | torch.arange(n, device=z.device)).values
        occupied = occupancy(own, occupancy_bits_for(n))
        live = torch.ones(n, dtype=torch.bool, device=z.device)
        parts = []
        for i, j, d2 in self._verified(z, records, bits, occupied, z, live, cubes, standardised=True):
            other = i != j
            parts.append((i[other], j[other], d2[other]))
        if not parts:
            empty = torch.zeros(0, dtype=torch.int64, device=z.device)
            return empty, empty, torch.zeros(0, dtype=torch.float32, device=z.device)
        i, j, d2 = (torch.cat(x) for x in zip(*parts, strict=True))
        pair, order = torch.sort((i << bits) | j)
        first = torch.ones_like(pair, dtype=torch.bool)
        first[1:] = pair[1:] != pair[:-1]
        order = order[first]
        return i[order], j[order], d2[order]

    def _verified(
        self,
        z: torch.Tensor,
        records: torch.Tensor,
        slot_bits: int,
        occupied: torch.Tensor,
        keys: torch.Tensor,
        live: torch.Tensor,
        cubes: tuple[torch.Tensor, torch.Tensor] | None = None,
        standardised: bool = False,
    ):
        """Yield, chunk by chunk of queries, the candidates ``(query, slot, d2)`` that are live and within
        delta (candidates = the records of the query's occupied cubes; duplicates possible)."""
        M = z.shape[0]
        if M == 0 or records.numel() == 0:
            return
        hashes, valid = self.query_cubes(z) if cubes is None else cubes  # [M, 2^d]
        flat = hashes.view(-1)
        valid = valid.view(-1) & occupied.index_select(0, bucket(flat, occupied.numel().bit_length() - 1))
        searched = valid.nonzero().squeeze(1)  # (query, cube) pairs worth a search
        if searched.numel() == 0:
            return
        wanted = flat.index_select(0, searched)
        low = torch.searchsorted(records, wanted << slot_bits)
        counts = torch.searchsorted(records, (wanted + 1) << slot_bits) - low
        nonempty = counts.nonzero().squeeze(1)
        if nonempty.numel() == 0:
            return
        counts, low = counts.index_select(0, nonempty), low.index_select(0, nonempty)
        owner = searched.index_select(0, nonempty) // hashes.shape[1]  # the query of each searched cube
        # Chunks of cubes holding at most MAX_CANDIDATES candidates (one cube may exceed it).
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
        mask = (1 << slot_bits) - 1
        for start, stop in itertools.pairwise(bounds):
            c = counts[start:stop]
            n = int(c.sum())
            if c.numel() == n:  # the common case: one record per cube
                index, query = low[start:stop], owner[start:stop]
            else:
                run_start = torch.repeat_interleave(c.cumsum(0) - c, c, output_size=n)
                index = torch.repeat_interleave(low[start:stop], c, output_size=n)
                index += torch.arange(n, device=z.device) - run_start
                query = torch.repeat_interleave(owner[start:stop], c, output_size=n)
            slot = records.index_select(0, index) & mask
            ok = live.index_select(0, slot)
            query, slot = query[ok], slot[ok]
            candidate = keys.index_select(0, slot)
            if not standardised:
                candidate = self.standardise(candidate)
            mine = z.index_select(0, query)
            d2 = squared_distance(mine, candidate)
            close = self.matches(mine, candidate, d2)
            yield query[close], slot[close], d2[close]

    def matches(self, a: torch.Tensor, b: torch.Tensor, d2: torch.Tensor | None = None) -> torch.Tensor:
        """Whether standardised keys ``a`` and ``b`` ``[..., d]`` are within delta (this index's shape);
        ``d2`` may pass their :func:`squared_distance`."""
        if self.shape == "box":
            return (a - b).abs().amax(-1) <= self.delta_f32
        return (squared_distance(a, b) if d2 is None else d2) < self.delta_sq
