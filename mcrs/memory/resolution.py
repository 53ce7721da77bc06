"""Algorithm 1's batched resolution: what a batch of transitions does to the episodic buffer D_E.

It works over arrays and the index only. :func:`in_order` lays a batch out in the algorithm's order,
:func:`resolve` reads the stored entries (:class:`Stored`, views never written) and the
:class:`~mcrs.memory.index.GridIndex` of the live keys and returns the batch's net effect
(:class:`Outcome`), and :func:`apply_outcome` writes it. :class:`~mcrs.memory.episodic.EpisodicMemory` owns
the storage and drives the three.

Insertion: the transitions of a batch ``[E, T]`` are taken episode by episode, each walked backwards, with
``R_t = r_t + gamma R_{t+1}`` and ``R_T = 0``. The nearest key within delta is updated when ``H < R``: H,
key, state and step are replaced (a memory shift). With no key within delta a new entry ``(x, R, s, t)`` is
added. The result equals that of this sequential loop. A transition with no batch key within delta that
shares no stored neighbour with another transition cannot interact with the rest, so it is resolved from
one batched look-up; only the few others are walked in order.

EMU (``track_desirability``): each entry also counts N_call (hits) and N_xi (hits from desirable
transitions) and carries xi (reached by a desirable transition). A transition is desirable when its episode
is, or when a later transition of its episode hit an entry with xi set (EMU's optimality propagation). On a
hit N_call += 1 and N_xi += desirable. The entry shifts when ``H < R`` or when a desirable transition meets
an entry with xi False; the shift sets ``H <- R``, possibly lower in the second case as EMU's reference
does, and ``xi <- xi or desirable``. With ``counter_reset`` (EMU's ``flag_memory_cnt_reset``, off by
default) the second kind of shift restarts N_call = N_xi = 1. A new entry starts with N_call = 1 and N_xi =
xi = desirable. Tracking walks every transition in order, since the propagation chains them."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import torch

from mcrs.memory.index import GridIndex


def discounted_returns(reward: torch.Tensor, gamma: float) -> torch.Tensor:
    """Return ``R_t = r_t + gamma R_{t+1}``, ``R_T = 0``, over the last dimension in float32. One numpy loop
    over T, multiplying then adding without fused multiply-add, rounds every element the same way and costs
    a tenth of the torch ops."""
    r = reward.detach().to("cpu", torch.float32).numpy()
    returns = np.empty_like(r)
    running = np.zeros(r.shape[:-1], dtype=np.float32)
    g = np.float32(gamma)
    for t in range(r.shape[-1] - 1, -1, -1):
        running = r[..., t] + g * running
        returns[..., t] = running
    return torch.from_numpy(returns).to(reward.device)


class Transitions(NamedTuple):
    """A batch of whole episodes ``[E, T]`` in Algorithm 1's order: transition ``j = e * T + (T - 1 - t)``."""

    flat: torch.Tensor  # [n] int64: the row e * T + t of transition j in the flattened batch
    returns: torch.Tensor  # [n] float32: R_t = r_t + gamma R_{t+1}, R_T = 0
    step: torch.Tensor  # [n] int16: t
    wanted: torch.Tensor  # [n] bool: its episode is desirable (EMU; all False when not given)


def in_order(reward: torch.Tensor, gamma: float, desirable: torch.Tensor | None = None) -> Transitions:
    """Return the transitions of ``reward [E, T]`` and ``desirable [E]`` in the order Algorithm 1 walks them."""
    E, T = reward.shape
    dev = reward.device
    flat = (torch.arange(E, device=dev).unsqueeze(1) * T + torch.arange(T - 1, -1, -1, device=dev)).reshape(
        -1
    )
    returns = discounted_returns(reward, gamma).reshape(-1)[flat]
    step = (T - 1 - torch.arange(T, device=dev, dtype=torch.int16)).repeat(E)
    if desirable is None:
        wanted = torch.zeros(E * T, dtype=torch.bool, device=dev)
    else:
        wanted = desirable.to(dev, torch.bool).repeat_interleave(T)
    return Transitions(flat, returns, step, wanted)


@dataclass(frozen=True)
class Stored:
    """The stored entries as resolution reads them: views of the memory's own ``[capacity]`` arrays."""

    keys: torch.Tensor  # [C, key_dim] float32 raw keys
    live: torch.Tensor  # [C] bool
    returns: torch.Tensor  # [C] float32: H
    n_call: torch.Tensor | None = None  # [C] int32 EMU counters; None without desirability tracking
    n_xi: torch.Tensor | None = None  # [C] int32
    xi: torch.Tensor | None = None  # [C] bool

    @property
    def capacity(self) -> int:
        return self.keys.shape[0]

    @property
    def track(self) -> bool:
        """Whether EMU's desirability is tracked."""
        return self.n_call is not None


class Neighbours(NamedTuple):
    """Pairs of keys within delta, sorted by ``asker`` then ``other``. ``asker [P]`` is a transition, ``other
    [P]`` a stored slot or another transition, ``d2 [P]`` their squared distance."""

    asker: torch.Tensor
    other: torch.Tensor
    d2: torch.Tensor


@dataclass
class Outcome:
    """The net effect of a batch on the memory: slots, and the transitions whose data they take."""

    new_from: torch.Tensor  # [nu] transitions that create an entry, in order (they take the next slots)
    shift_slots: torch.Tensor  # existing or new slots whose key/state/H end up from another transition
    shift_from: torch.Tensor  # that transition
    shift_is_new: torch.Tensor  # whether the shifted slot was created by this batch
    count_slots: torch.Tensor  # slots whose EMU counters changed (hits on existing entries)
    n_call: torch.Tensor
    n_xi: torch.Tensor
    xi: torch.Tensor
    hits: int
    shifts: int


def resolve(
    index: GridIndex,
    stored: Stored,
    z: torch.Tensor,
    R: torch.Tensor,
    wanted: torch.Tensor,
    write: int,
    T: int,
    counter_reset: bool = False,
) -> Outcome:
    """Apply Algorithm 1 to the transitions ``z [n, d]`` against the ``stored`` entries, whose live keys
    ``index`` holds.

    ``z`` are standardised keys in order, ``T`` per episode, ``R [n]`` their returns, ``wanted [n]`` their
    episodes' desirability and ``write`` the slot of the first new entry. Independent transitions are
    resolved from the batched look-up and interacting ones sequentially; with desirability tracking all are
    walked in order."""
    dev, track = stored.keys.device, stored.track
    n = z.shape[0]
    cubes = index.query_cubes(z)
    near = Neighbours(*index.within(z, stored.keys, stored.live, cubes))  # stored neighbours
    pairs = Neighbours(*index.pairs(z, cubes))  # batch neighbours
    query, slot, d2 = near

    interacting = torch.zeros(n, dtype=torch.bool, device=dev)
    interacting[pairs.asker] = True
    if track:
        interacting[:] = True
    elif slot.numel():
        _, inverse, shared = torch.unique(slot, return_inverse=True, return_counts=True)
        interacting[query[shared[inverse] > 1]] = True

    # Nearest stored neighbour (lowest slot on ties) of every transition.
    nearest = torch.full((n,), -1, dtype=torch.int64, device=dev)
    if slot.numel():
        best = torch.full((n,), torch.iinfo(torch.int64).max, dtype=torch.int64, device=dev)
        best.scatter_reduce_(0, query, (d2.view(torch.int32).to(torch.int64) << 32) | slot, "amin")
        nearest = torch.where(best != torch.iinfo(torch.int64).max, best & 0xFFFFFFFF, -1)

    free = ~interacting
    hit_j = (free & (nearest >= 0)).nonzero().squeeze(1)
    new_free = free & (nearest < 0)
    target = nearest[hit_j]
    shift = stored.returns[target] < R[hit_j]
    shift_slots, shift_from = target[shift], hit_j[shift]
    hits, shifts = int(hit_j.numel()), int(shift.sum())
    new_mask = new_free
    empty = torch.zeros(0, dtype=torch.int64, device=dev)
    count_slots, n_call, n_xi, xi = empty, empty.int(), empty.int(), empty.bool()

    group = interacting.nonzero().squeeze(1)
    shift_is_new = torch.zeros(shift_slots.numel(), dtype=torch.bool, device=dev)
    if group.numel():
        seq = _sequential(
            stored, group, near, pairs, R, wanted, new_free, write=write, T=T, counter_reset=counter_reset
        )
        new_mask = new_free.clone()
        new_mask[seq["new"]] = True
        shift_slots = torch.cat([shift_slots, seq["owner_slots"]])
        shift_from = torch.cat([shift_from, seq["owner_from"]])
        shift_is_new = torch.cat([shift_is_new, seq["owner_is_new"]])
        hits, shifts = hits + seq["hits"], shifts + seq["shifts"]
        if track:
            count_slots, n_call, n_xi, xi = seq["count_slots"], seq["n_call"], seq["n_xi"], seq["xi"]
    return Outcome(
        new_from=new_mask.nonzero().squeeze(1),
        shift_slots=shift_slots,
        shift_from=shift_from,
        shift_is_new=shift_is_new,
        count_slots=count_slots,
        n_call=n_call,
        n_xi=n_xi,
        xi=xi,
        hits=hits,
        shifts=shifts,
    )


def _by_distance(
    owner: torch.Tensor, item: torch.Tensor, d2: torch.Tensor, n: int
) -> tuple[list[int], list[int], list[float]]:
    """Return candidate lists in CSR form ``(start [n + 1], item, d2)``, each owner's sorted by distance. The
    candidates of owner j are at ``start[j]:start[j + 1]``; ties keep the input order, which is sorted by
    owner then item."""
    order = torch.sort((owner << 32) | d2.view(torch.int32).to(torch.int64), stable=True).indices
    counts = torch.bincount(owner, minlength=n)
    start = torch.cat([counts.new_zeros(1), counts.cumsum(0)])
    return start.tolist(), item[order].tolist(), d2[order].tolist()


def _sequential(
    stored: Stored,
    group: torch.Tensor,
    near: Neighbours,
    pairs: Neighbours,
    returns: torch.Tensor,
    wanted: torch.Tensor,
    new_free: torch.Tensor,
    *,
    write: int,
    T: int,
    counter_reset: bool,
) -> dict[str, Any]:
    """Walk Algorithm 1 in order over the interacting transitions ``group``.

    ``near`` holds their stored neighbours and ``pairs`` their batch neighbours, each sorted by distance. A
    stored neighbour is valid while the entry still holds its old key, so the first valid one is the best.
    An earlier batch key is valid while some entry holds it, so those are scanned until the distance
    exceeds the best found. A new entry of transition j takes slot ``write + (new entries before j)``. With
    desirability tracking ``group`` is every transition and ``wanted`` spreads backwards within an episode
    from any hit on an entry with xi set."""
    dev, C, track = stored.keys.device, stored.capacity, stored.track
    in_group = torch.zeros_like(new_free)
    in_group[group] = True
    n = new_free.numel()
    sel = in_group[near.asker]
    s_start, g_slot, g_d2 = _by_distance(near.asker[sel], near.other[sel], near.d2[sel], n)
    sel = pairs.other < pairs.asker  # neighbours earlier in the order
    e_start, e_from, e_d2 = _by_distance(pairs.asker[sel], pairs.other[sel], pairs.d2[sel], n)
    touched = sorted(set(g_slot))
    touched_t = torch.tensor(touched, dtype=torch.int64, device=dev)
    H = dict(zip(touched, stored.returns[touched_t].tolist(), strict=True))
    if track:
        n_call = dict(zip(touched, stored.n_call[touched_t].tolist(), strict=True))
        n_xi = dict(zip(touched, stored.n_xi[touched_t].tolist(), strict=True))
        xi = dict(zip(touched, stored.xi[touched_t].tolist(), strict=True))
    members = group.tolist()
    new_before = (torch.cumsum(new_free.to(torch.int64), 0) - new_free.to(torch.int64))[group].tolist()
    R_g, want_g = returns[group].tolist(), wanted[group].tolist()
    reset = counter_reset
    propagated_episode = -1  # the episode whose later transitions hit a desirable entry

    owner: dict[int, int] = {}  # slot -> transition whose key/state it holds now (changed in this batch)
    holder: dict[int, int] = {}  # transition -> slot holding its key
    created: set[int] = set()
    counted: set[int] = set()
    new: list[int] = []
    hits = shifts = 0
    for j, before, r, want in zip(members, new_before, R_g, want_g, strict=True):
        want = want or (track and j // T == propagated_episode)
        best: tuple[float, int] | None = None
        for k in range(s_start[j], s_start[j + 1]):
            if g_slot[k] not in owner:
                best = (g_d2[k], g_slot[k])
                break
        for k in range(e_start[j], e_start[j + 1]):
            d = e_d2[k]
            if best is not None and d > best[0]:
                break
            s = holder.get(e_from[k])
            if s is not None and (best is None or (d, s) < best):
                best = (d, s)
        if best is None:  # a new entry
            s = (write + before + len(new)) % C
            new.append(j)
            created.add(s)
            owner[s], holder[j], H[s] = j, s, r
            if track:
                n_call[s], n_xi[s], xi[s] = 1, int(want), bool(want)
            continue
        s = best[1]
        hits += 1
        if track:
            n_call[s] += 1
            n_xi[s] += int(want)
            counted.add(s)
        desirability_shift = track and want and not xi[s]
        if H[s] < r or desirability_shift:
            shifts += 1
            if s in owner:
                del holder[owner[s]]
            owner[s], holder[j], H[s] = j, s, r
            if track:
                xi[s] = xi[s] or bool(want)
                if desirability_shift and reset:
                    n_call[s], n_xi[s] = 1, 1
        if track and xi[s]:  # EMU's optimality propagation: earlier states of this episode are desirable
            propagated_episode = j // T

    counters = (counted, n_call, n_xi, xi) if track else None
    return _walked(dev, new, owner, created, hits, shifts, counters)


def _walked(
    dev: torch.device,
    new: list[int],
    owner: dict[int, int],
    created: set[int],
    hits: int,
    shifts: int,
    counters: tuple[set[int], dict[int, int], dict[int, int], dict[int, bool]] | None,
) -> dict[str, Any]:
    """Return what the walk of :func:`_sequential` did as tensors: new entries, shifted slots and, for EMU,
    changed counters."""
    owner_slots = sorted(owner)
    result: dict[str, Any] = {
        "new": torch.tensor(new, dtype=torch.int64, device=dev),
        "owner_slots": torch.tensor(owner_slots, dtype=torch.int64, device=dev),
        "owner_from": torch.tensor([owner[s] for s in owner_slots], dtype=torch.int64, device=dev),
        "owner_is_new": torch.tensor([s in created for s in owner_slots], dtype=torch.bool, device=dev),
        "hits": hits,
        "shifts": shifts,
    }
    if counters is not None:  # every slot this group changed, new entries included (their start values)
        counted, n_call, n_xi, xi = counters
        slots = sorted(counted | created)
        result.update(
            count_slots=torch.tensor(slots, dtype=torch.int64, device=dev),
            n_call=torch.tensor([n_call[s] for s in slots], dtype=torch.int32, device=dev),
            n_xi=torch.tensor([n_xi[s] for s in slots], dtype=torch.int32, device=dev),
            xi=torch.tensor([xi[s] for s in slots], dtype=torch.bool, device=dev),
        )
    return result


# ---------------------------------------------------------------------------------------------- applying
def apply_outcome(
    outcome: Outcome,
    write: int,
    flat: torch.Tensor,
    live: torch.Tensor,
    by_transition: Sequence[tuple[torch.Tensor, torch.Tensor]],
    by_row: Sequence[tuple[torch.Tensor, torch.Tensor]],
) -> torch.Tensor:
    """Write ``outcome``'s new entries and shifts into the memory's ``[C, ...]`` arrays; return the new slots.

    ``by_transition`` pairs an array with its batch values in transition order, ``by_row`` with values in
    the batch's row order, read through ``flat``. New entries take consecutive ring slots from ``write``
    and are marked ``live``; the shifts come after, since a new entry may be shifted later in the same
    batch. EMU's counters are the caller's to write."""
    C = live.shape[0]
    nu = outcome.new_from.numel()
    first = min(nu, C - write)
    for slot, lo, hi in ((write, 0, first), (0, first, nu)):
        if hi > lo:
            source = outcome.new_from[lo:hi]
            for array, values in by_transition:
                array[slot : slot + hi - lo] = values.index_select(0, source)
            for array, values in by_row:
                array.view(C, -1)[slot : slot + hi - lo] = values.index_select(0, flat[source])
            live[slot : slot + hi - lo] = True
    if outcome.shift_slots.numel():
        source = outcome.shift_from
        for array, values in by_transition:
            array.index_copy_(0, outcome.shift_slots, values.index_select(0, source))
        for array, values in by_row:
            _row_view(array).index_copy_(
                0, outcome.shift_slots, _row_view(values.index_select(0, flat[source]))
            )
    return (write + torch.arange(nu, device=live.device)) % C


def _row_view(t: torch.Tensor) -> torch.Tensor:
    """View ``t [N, ...]`` as ``[N, m]`` of the widest integer type dividing a row's bytes, since row copies
    of narrow types are slow."""
    t = t.view(t.shape[0], -1)
    row_bytes = t.shape[1] * t.element_size()
    for dtype in (torch.int64, torch.int32, torch.int16):
        if row_bytes % dtype.itemsize == 0:
            return t.view(torch.uint8).view(dtype)
    return t
