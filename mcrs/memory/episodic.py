"""The episodic buffer D_E (paper Algorithm 1), batched and exact.

An entry holds a key ``x = phi(s, t/T)`` (float32 ``[key_dim]``), the highest return ``H`` seen from it,
the state ``s`` in the compact form of :class:`~mcrs.memory.codec.StateCodec`, the step ``t`` and the id of
the episode that wrote it, so a look-up can tell another trajectory's memory from its own. Columns are
preallocated tensors of ``capacity`` rows (1M map20 entries take about 0.9 GiB). Look-ups use the exact
grid index of :mod:`mcrs.memory.index`, kept current at every insertion; :mod:`mcrs.memory.resolution`
resolves each batch. Eviction is a FIFO ring: before a batch of n transitions is resolved, the oldest
entries are evicted so that the whole batch fits. A shifted entry keeps its slot and its age.

The key standardisation statistics are recomputed at an index rebuild, and only then: when an insertion
finds the buffer empty (from that batch's keys), when the buffer has doubled since the last refresh, when
stale index records exceed ``stale_fraction`` of the live entries, and at
:meth:`EpisodicMemory.refresh_keys`. :meth:`EpisodicMemory.load_state_dict` restores the saved statistics
instead (format: :mod:`mcrs.memory.persistence`)."""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from mcrs.memory.codec import StateCodec
from mcrs.memory.index import MAX_KEY_DIM, GridIndex
from mcrs.memory.persistence import UNKNOWN_EPISODE, memory_state, restore_memory
from mcrs.memory.resolution import Stored, apply_outcome, in_order, resolve

MAX_STEPS_LIMIT = 2**15  # steps are stored as int16


@dataclass
class InsertStats:
    """What one :meth:`EpisodicMemory.insert` did."""

    transitions: int  # transitions offered (E * T)
    new: int  # new entries
    hits: int  # transitions that found a key within delta (shifts included)
    shifted: int  # memory shifts (key, state and return replaced)
    evicted: int  # oldest entries evicted before the batch


def _check_int(name: str, value: Any, low: int, high: int | None = None) -> int:
    if (
        isinstance(value, bool)
        or not isinstance(value, int)
        or value < low
        or (high is not None and value > high)
    ):
        allowed = f"an int >= {low}" if high is None else f"an int in [{low}, {high}]"
        raise ValueError(f"{name} must be {allowed}, got {value!r}")
    return value


class EpisodicMemory:
    """D_E: keys, highest returns and compact states of up to ``capacity`` visited states.

    Args:
        embedding: phi, a module with ``forward(state [..., D], time [...]) -> [..., key_dim]`` and an int
            ``key_dim`` attribute; called without gradients.
        codec: the :class:`StateCodec` of the env's map.
        capacity: number of entries (table 3: 1M).
        tolerance: the match tolerance on standardised keys (:func:`mcrs.memory.delta.match_tolerance`).
        gamma: discount of the returns H.
        max_steps: T of the env, for the time input ``t / T``; defaults to the codec's.
        track_desirability: keep EMU's N_call, N_xi and xi.
        counter_reset: EMU's ``flag_memory_cnt_reset``: a desirability shift restarts N_call = N_xi = 1.
        shape: ``"ball"`` or EMU's ``"box"`` (:mod:`mcrs.memory.index`).
        stale_fraction: rebuild the index when stale records exceed this fraction of the entries.
        check_states: check that a sample of each inserted batch has the maps of its counts; off only for
            synthetic states in tests.
    """

    def __init__(
        self,
        embedding: nn.Module,
        codec: StateCodec,
        capacity: int = 1_000_000,
        tolerance: float = 1.3e-3,
        gamma: float = 0.99,
        max_steps: int | None = None,
        track_desirability: bool = False,
        device: torch.device | str = "cpu",
        shape: str = "ball",
        counter_reset: bool = False,
        stale_fraction: float = 0.25,
        check_states: bool = True,
    ) -> None:
        key_dim = getattr(embedding, "key_dim", None)
        _check_int("embedding.key_dim", key_dim, 1, MAX_KEY_DIM)
        _check_int("capacity", capacity, 1, 2**31 - 1)
        if (
            isinstance(tolerance, bool)
            or not isinstance(tolerance, (int, float))
            or not 0 < tolerance < math.inf
        ):
            raise ValueError(f"tolerance must be a finite number > 0, got {tolerance!r}")
        if isinstance(gamma, bool) or not isinstance(gamma, (int, float)) or not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be a number in [0, 1], got {gamma!r}")
        max_steps = codec.config.max_steps if max_steps is None else max_steps
        _check_int("max_steps", max_steps, 1, MAX_STEPS_LIMIT - 1)
        if (
            isinstance(stale_fraction, bool)
            or not isinstance(stale_fraction, (int, float))
            or not stale_fraction > 0
        ):
            raise ValueError(f"stale_fraction must be a number > 0, got {stale_fraction!r}")
        self.embedding, self.codec = embedding, codec
        self.key_dim, self.capacity, self.tolerance = int(key_dim), capacity, float(tolerance)
        self.gamma, self.max_steps = float(gamma), max_steps
        self.track_desirability = bool(track_desirability)
        self.counter_reset = bool(counter_reset)
        self.device = torch.device(device)
        self.stale_fraction = float(stale_fraction)
        self.check_states = bool(check_states)
        C, dev = capacity, self.device
        self.keys = torch.zeros(C, self.key_dim, dtype=torch.float32, device=dev)
        self.returns = torch.zeros(C, dtype=torch.float32, device=dev)  # H
        self.step = torch.zeros(C, dtype=torch.int16, device=dev)
        # torch.empty: the large arrays only become resident as entries are written.
        self.codes = torch.empty(C, codec.n_cells, 2, dtype=torch.uint8, device=dev)
        self.positions = torch.empty(C, codec.n_positions, 2, dtype=codec.position_dtype, device=dev)
        self.live = torch.zeros(C, dtype=torch.bool, device=dev)
        self.episode = torch.full((C,), UNKNOWN_EPISODE, dtype=torch.int64, device=dev)
        if self.track_desirability:
            self.n_call = torch.zeros(C, dtype=torch.int32, device=dev)
            self.n_xi = torch.zeros(C, dtype=torch.int32, device=dev)
            self.xi = torch.zeros(C, dtype=torch.bool, device=dev)
        self.start = 0  # slot of the oldest entry
        self.size = 0
        self.stats_size = 0  # entries when the statistics were last refreshed
        self.index = GridIndex(self.key_dim, self.tolerance, C, dev, shape=shape)
        self.shape = shape

    # ------------------------------------------------------------------------------------ basics
    def __len__(self) -> int:
        return self.size

    def columns(self) -> dict[str, torch.Tensor]:
        """Every per-entry ``[capacity, ...]`` array except ``live``."""
        columns = {"keys": self.keys, "returns": self.returns, "step": self.step, "codes": self.codes}
        columns.update(positions=self.positions, episode=self.episode)
        if self.track_desirability:
            columns.update(n_call=self.n_call, n_xi=self.n_xi, xi=self.xi)
        return columns

    def nbytes(self) -> int:
        """Bytes held by the buffer: storage, index records and decode tables."""
        tensors = [*self.columns().values(), self.live]
        return sum(t.numel() * t.element_size() for t in tensors) + self.index.nbytes() + self.codec.nbytes()

    def live_slots(self) -> torch.Tensor:
        """Slots of the live entries, oldest first."""
        return (self.start + torch.arange(self.size, device=self.device)) % self.capacity

    def _live_ranges(self) -> Iterator[tuple[int, int]]:
        """The live slots as at most two contiguous ranges ``[a, b)``, oldest first."""
        end = self.start + self.size
        yield self.start, min(end, self.capacity)
        if end > self.capacity:
            yield 0, end - self.capacity

    def _stored(self) -> Stored:
        """Views of the arrays that Algorithm 1's resolution reads."""
        if not self.track_desirability:
            return Stored(self.keys, self.live, self.returns)
        return Stored(self.keys, self.live, self.returns, self.n_call, self.n_xi, self.xi)

    def statistics(self) -> dict[str, float]:
        """Scalars for logging."""
        stats = {
            "size": float(self.size),
            "capacity": float(self.capacity),
            "fill": self.size / self.capacity,
            "index_records": float(len(self.index)),
            "stale_records": float(len(self.index) - self.size),
            "count_bytes": float(self.codes.element_size()),
            "nbytes": float(self.nbytes()),
        }
        if self.size:
            slots = self.live_slots()
            H = self.returns[slots]
            stats.update(return_mean=H.mean().item(), return_max=H.max().item(), return_min=H.min().item())
            if self.track_desirability:
                calls = self.n_call[slots].float()
                stats.update(
                    n_call_mean=calls.mean().item(),
                    desirable_ratio_mean=(self.n_xi[slots].float() / calls).mean().item(),
                    xi_fraction=self.xi[slots].float().mean().item(),
                )
        return stats

    # ------------------------------------------------------------------------------------ embedding
    def _embed(self, state: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        """Keys of ``state [..., D]`` at ``time [...]`` (float32, on the memory's device)."""
        first = next(iter(self.embedding.parameters()), None)
        if first is None:
            first = next(iter(self.embedding.buffers()), None)
        device = first.device if first is not None else self.device
        with torch.no_grad():
            keys = self.embedding(state.to(device, torch.float32), time.to(device, torch.float32))
        if keys.shape != (*state.shape[:-1], self.key_dim):
            raise ValueError(
                f"the embedding returned keys of shape {tuple(keys.shape)}, expected {(*state.shape[:-1], self.key_dim)}"
            )
        return keys.to(self.device, torch.float32)

    def normalised_time(self, step: torch.Tensor) -> torch.Tensor:
        """``t / T`` in float32, as the memory computes it for the embedding."""
        return step.to(torch.float32) / self.max_steps

    # ------------------------------------------------------------------------------------ look-ups
    def lookup(
        self, state: torch.Tensor, time: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Embed ``state [..., D]`` at ``time [...]`` (t/T) and look the keys up; return ``(H, hit, slot)``,
        each ``[...]``."""
        keys = self._embed(state, torch.as_tensor(time).expand(state.shape[:-1]))
        value, hit, slot = self.lookup_keys(keys.reshape(-1, self.key_dim))
        lead = state.shape[:-1]
        return value.view(lead), hit.view(lead), slot.view(lead)

    def lookup_keys(self, keys: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Look up raw keys ``[M, key_dim]``; return ``(H [M], hit [M], slot [M])`` with H = 0 and slot = -1
        on a miss."""
        keys = keys.to(self.device, torch.float32)
        slot, _ = self.index.nearest(self.index.standardise(keys), self.keys, self.live)
        hit = slot >= 0
        value = torch.where(hit, self.returns[slot.clamp(min=0)], 0.0)
        return value, hit, slot

    def written_by(self, slot: torch.Tensor) -> torch.Tensor:
        """Return the id of the episode that wrote each entry of ``slot``; -1 for slot -1 or unknown."""
        slot = slot.to(self.device)
        return torch.where(slot >= 0, self.episode[slot.clamp(min=0)], UNKNOWN_EPISODE)

    def desirable_ratio(self, slot: torch.Tensor) -> torch.Tensor:
        """Return EMU's N_xi / N_call of the entries ``slot`` as float32; 0 where slot is -1."""
        if not self.track_desirability:
            raise RuntimeError("desirable_ratio needs track_desirability=True")
        slot = slot.to(self.device)
        safe = slot.clamp(min=0)
        ratio = self.n_xi[safe].to(torch.float32) / self.n_call[safe].clamp(min=1).to(torch.float32)
        return torch.where(slot >= 0, ratio, 0.0)

    def sample(
        self, n: int, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Draw ``n`` entries uniformly with replacement; return ``(state [n, D], time [n], H [n])``."""
        if self.size == 0:
            raise RuntimeError("cannot sample from an empty episodic memory")
        draw = torch.randint(self.size, (n,), generator=generator).to(self.device)
        slots = (self.start + draw) % self.capacity
        state = self.codec.decode(self.codes[slots], self.positions[slots])
        return state, self.normalised_time(self.step[slots]), self.returns[slots].clone()

    def states(self, slots: torch.Tensor) -> torch.Tensor:
        """Decoded states ``[n, D]`` of ``slots``."""
        slots = slots.to(self.device)
        return self.codec.decode(self.codes[slots], self.positions[slots])

    # ------------------------------------------------------------------------------------ insertion
    @torch.inference_mode(False)  # tensors it allocates persist: they must not be inference tensors
    def insert(
        self,
        state: torch.Tensor,
        counts: torch.Tensor,
        reward: torch.Tensor,
        desirable: torch.Tensor | None = None,
        episode: torch.Tensor | None = None,
    ) -> InsertStats:
        """Apply Algorithm 1 to whole episodes.

        ``T`` may be ``max_steps + 1``: the terminal state s_T is then stored with H(s_T) = 0, as EMC
        stores it, so that the last transition has a memory to look up.

        Args:
            state: ``[E, T, D]``.
            counts: ``[E, T, cells, 2]``, the env's ``state_counts`` of the same states.
            reward: ``[E, T]``, r_t of s_t -> s_{t+1}.
            desirable: ``[E]``, EMU's flag; required when tracking desirability.
            episode: ``[E]`` int ids recorded with the entries they write; -1 when not given.
        """
        E, T = self._check_batch(state, counts, reward, desirable, episode)
        n = E * T
        if n == 0:
            return InsertStats(0, 0, 0, 0, 0)
        dev, C = self.device, self.capacity
        state, counts, reward = state.to(dev), counts.to(dev), reward.to(dev)

        # Transition j = e * T + (T - 1 - t): episode by episode, backwards in time.
        flat, returns, step, wanted = in_order(
            reward, self.gamma, desirable if self.track_desirability else None
        )
        x = self._batch_keys(state, flat)
        if episode is None:
            episode = torch.full((E,), UNKNOWN_EPISODE, dtype=torch.int64)
        written = episode.to(dev, torch.int64).repeat_interleave(T)
        codes, positions = self._encode(state, counts)

        evicted = self._evict(max(0, self.size + n - C))
        if self.size == 0:
            self.index.clear()
            self.index.set_statistics(x)
            self.stats_size = n
        z = self.index.standardise(x)
        write = (self.start + self.size) % C  # slot of the first new entry
        outcome = resolve(self.index, self._stored(), z, returns, wanted, write, T, self.counter_reset)

        # Apply: the shifted old slots' cubes first (their keys are about to change), then the writes.
        old_slots = outcome.shift_slots[~outcome.shift_is_new]
        new_slots = apply_outcome(
            outcome,
            write,
            flat,
            self.live,
            by_transition=[
                (self.keys, x),
                (self.returns, returns),
                (self.step, step),
                (self.episode, written),
            ],
            by_row=[(self.codes, codes.view(n, -1)), (self.positions, positions.view(n, -1))],
        )
        if self.track_desirability:  # every changed slot (new ones included) is in count_slots
            self.n_call[outcome.count_slots] = outcome.n_call
            self.n_xi[outcome.count_slots] = outcome.n_xi
            self.xi[outcome.count_slots] = outcome.xi
        self.size += new_slots.numel()

        # Index: every slot whose key was written (new ones and shifted old ones).
        fresh = torch.cat([new_slots, old_slots])
        self.index.add(self.keys.index_select(0, fresh), fresh)
        self._maintain()
        return InsertStats(
            transitions=n,
            new=int(new_slots.numel()),
            hits=outcome.hits,
            shifted=outcome.shifts,
            evicted=evicted,
        )

    def _batch_keys(self, state: torch.Tensor, flat: torch.Tensor) -> torch.Tensor:
        """The keys x = phi(s, t/T) of an ``[E, T, D]`` batch, in the transition order ``flat`` gives."""
        E, T = state.shape[:2]
        time = self.normalised_time(torch.arange(T, device=self.device))
        x = self._embed(state, time.expand(E, T)).reshape(E * T, self.key_dim)[flat]
        if not torch.isfinite(x).all():
            raise ValueError("the embedding produced non-finite keys")
        return x

    def _encode(self, state: torch.Tensor, counts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The batch's states in the codec's compact form, in the storage's dtype, which is promoted
        when a count outgrows it."""
        n = state.shape[0] * state.shape[1]
        codes, positions = self.codec.encode(
            counts.reshape(n, self.codec.n_cells, 2),
            state.reshape(n, self.codec.state_dim),
            check_maps=self.check_states,
        )
        if codes.element_size() > self.codes.element_size():
            self.codes = self.codes.to(codes.dtype)  # promotion: a count above 255 arrived
        return codes.to(self.codes.dtype), positions

    def _check_batch(
        self,
        state: torch.Tensor,
        counts: torch.Tensor,
        reward: torch.Tensor,
        desirable: torch.Tensor | None,
        episode: torch.Tensor | None,
    ) -> tuple[int, int]:
        """Check the shapes :meth:`insert` needs and that the batch fits; return ``(E, T)``."""
        D, cells = self.codec.state_dim, self.codec.n_cells
        if state.dim() != 3 or state.shape[2] != D:
            raise ValueError(f"state must have shape [E, T, {D}], got {tuple(state.shape)}")
        E, T = state.shape[:2]
        if counts.shape != (E, T, cells, 2):
            raise ValueError(f"counts must have shape {[E, T, cells, 2]}, got {tuple(counts.shape)}")
        if reward.shape != (E, T):
            raise ValueError(f"reward must have shape {[E, T]}, got {tuple(reward.shape)}")
        if self.max_steps + 1 < T:
            raise ValueError(
                f"episodes have {T} states, more than max_steps + 1 = {self.max_steps + 1} (s_0 .. s_T)"
            )
        n = E * T
        if n > self.capacity:
            raise ValueError(
                f"a batch of {n} transitions does not fit capacity={self.capacity}: insert fewer"
            )
        if self.track_desirability and (desirable is None or desirable.shape != (E,)):
            raise ValueError(f"desirable must be a bool tensor of shape [{E}] with track_desirability")
        if episode is not None and episode.shape != (E,):
            raise ValueError(f"episode must be an int tensor of shape [{E}], got {tuple(episode.shape)}")
        return E, T

    def _evict(self, count: int) -> int:
        """Drop the ``count`` oldest entries."""
        if count:
            self.live[(self.start + torch.arange(count, device=self.device)) % self.capacity] = False
            self.start = (self.start + count) % self.capacity
            self.size -= count
        return count

    def _maintain(self) -> None:
        """Rebuild the index and refresh the statistics when it is stale or the buffer has doubled."""
        stale = len(self.index) - self.size
        if self.size >= 2 * max(self.stats_size, 1) or stale > self.stale_fraction * self.size:
            self.rebuild_index()

    def rebuild_index(self, refresh: bool = True) -> None:
        """Re-index every live entry; with ``refresh`` recompute the standardisation statistics first."""
        self.index.rebuild(self.keys, self.live_slots(), refresh=refresh)
        if refresh:
            self.stats_size = self.size

    # ------------------------------------------------------------------------------------ re-embedding
    def refresh_keys(self, chunk: int = 4096) -> None:
        """Re-embed every stored state with the current embedding, then rebuild the index and statistics.
        States are decoded ``chunk`` at a time into one reused buffer, small enough to keep the CNN's
        activations in cache."""
        _check_int("chunk", chunk, 1)
        buffer = torch.empty(min(chunk, max(self.size, 1)), self.codec.state_dim, device=self.device)
        with torch.inference_mode():
            for a, b in self._live_ranges():
                for lo in range(a, b, chunk):
                    hi = min(lo + chunk, b)
                    states = self.codec.decode(
                        self.codes[lo:hi], self.positions[lo:hi], out=buffer[: hi - lo]
                    )
                    keys = self._embed(states, self.normalised_time(self.step[lo:hi]))
                    if not torch.isfinite(keys).all():
                        self.rebuild_index()  # the keys written so far stay consistent with the index
                        raise ValueError("the embedding produced non-finite keys")
                    self.keys[lo:hi] = keys
        self.rebuild_index()

    # ------------------------------------------------------------------------------------ persistence
    def state_dict(self) -> dict[str, Any]:
        """Return the filled part (oldest first), the ring position, the statistics and the codec's identity.
        It holds only plain types, so ``torch.load(weights_only=True)`` reads it
        (:mod:`mcrs.memory.persistence`)."""
        return memory_state(self)

    @torch.inference_mode(False)
    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a :meth:`state_dict`, refusing one from another map or key_dim, or one that does not fit.

        With the same capacity the entries return to their slots, so look-ups answer exactly as before;
        otherwise they are laid out oldest first from slot 0. The saved statistics are restored, and this
        memory's own tolerance and gamma apply from now on."""
        restore_memory(self, state)
