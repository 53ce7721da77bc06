"""Compact, bit-exact storage of the env's global state for the episodic buffer D_E.

A map20 state is 880 float32 values (3.5 kB), too much for a million entries. The state is a function of
small integers (:class:`~mcrs.env.layout.StateLayout` says where each part lies):

- the maps m(U) and m(F) are ``belief_masses`` of the global counts ``state_counts [cells, 2]``;
- with ``no_fly_prior=known`` the no-fly cells read m(U) = m(F) = 0 whatever their counts
  (:meth:`StateCodec.clear_zones`);
- the positions of the ``P = N + Z + K`` UAVs, zones and targets are ``p.to(float32) / pos_scale``.

An entry stores the counts (``uint8`` while every count is <= 255, else ``int16``: 800 B for map20) and the
integer positions (``uint8 [P, 2]``: 80 B). :meth:`StateCodec.decode` rebuilds the float32 state bit for
bit from a table of ``belief_masses`` of every count pair, computed by the env's own function, and from the
env's division for the positions. The tests check it on real rollouts with ``torch.equal``. Every embedding
update re-embeds every stored state, hence the table."""

from __future__ import annotations

import sys
from typing import Any

import torch

from mcrs.env.belief import belief_masses
from mcrs.env.config import EnvConfig
from mcrs.env.layout import StateLayout

MAX_COUNT = 2**15 - 1  # the widest code, int16
U8_MAX = 255
# Tables for int16 codes cover the largest counts present; above this many entries the maps are computed
# with belief_masses directly.
MAX_TABLE_ENTRIES = 1 << 22
_LITTLE_ENDIAN = sys.byteorder == "little"
MAP_CHECKS = 64  # states of each encoded batch whose maps are checked against their counts


class StateCodec:
    """Encode env states ``[B, state_dim]`` as ``(codes [B, cells, 2], positions [B, P, 2])`` and back. The
    codec is valid only for the map of ``config`` (:meth:`identity`)."""

    def __init__(self, config: EnvConfig) -> None:
        self.config = config
        self.layout = layout = StateLayout.from_config(config)
        if layout.positions != slice(layout.map_dim, layout.state_dim):
            raise AssertionError(f"the codec expects the maps, then every position: got {layout}")
        self.n_cells = config.n_cells
        self.map_dim = layout.map_dim
        self.n_positions = layout.n_positions
        self.state_dim = layout.state_dim
        self.grid_max = (layout.width - 1, layout.height - 1)  # the largest cell coordinates
        self.position_dtype = torch.uint8 if max(self.grid_max) <= U8_MAX else torch.int16
        # The env's float32 scale, so that decode repeats its division exactly.
        self._pos_scale = torch.tensor(layout.pos_scale, dtype=torch.float32)
        self._grid_max = torch.tensor(self.grid_max, dtype=torch.float32)
        self.known_zones = config.no_fly_prior == "known"
        # The no-fly slots among the positions: UAVs come first, then the zones.
        self._zone_slots = slice(config.n_uavs, config.n_uavs + config.n_no_fly)
        self._tables: dict[tuple, torch.Tensor] = {}
        self._index: torch.Tensor | None = None

    # ------------------------------------------------------------------------------------------ identity
    def identity(self) -> dict[str, Any]:
        """Return what a stored state depends on, so that a memory saved for another map or sensor model is
        refused."""
        c = self.config
        return {
            "map": c.name,
            "width": c.width,
            "height": c.height,
            "n_uavs": c.n_uavs,
            "n_no_fly": c.n_no_fly,
            "n_targets": c.n_targets,
            "state_dim": c.state_dim,
            "max_steps": c.max_steps,
            "m_f": float(c.m_f),
            "m_e": float(c.m_e),
            "no_fly_prior": c.no_fly_prior,
        }

    def identity_mismatch(self, other: dict[str, Any]) -> str | None:
        """Return why states encoded under ``other`` cannot be decoded here, or None."""
        mine = self.identity()
        other = {"no_fly_prior": "unknown", **other}  # a memory saved before the field held unread zones
        diffs = [f"{k}: saved {other.get(k)!r}, here {v!r}" for k, v in mine.items() if other.get(k) != v]
        return "; ".join(diffs) if diffs else None

    # ------------------------------------------------------------------------------------------ encoding
    def encode(
        self, counts: torch.Tensor, state: torch.Tensor, check_maps: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Encode ``counts [B, cells, 2]`` and ``state [B, state_dim]`` as ``(codes, positions)``.

        ``codes`` are the counts as ``uint8`` when every count of the batch is <= 255, else ``int16``.
        ``positions [B, P, 2]`` are the cells recovered from the state and checked to reproduce it exactly.
        With ``check_maps``, up to ``MAP_CHECKS`` evenly spaced states are also checked to have the maps of
        their counts, which refuses counts of another step or sensor model."""
        B = state.shape[0] if state.dim() == 2 else -1
        if state.dim() != 2 or state.shape[1] != self.state_dim:
            raise ValueError(f"state must have shape [B, {self.state_dim}], got {tuple(state.shape)}")
        if counts.shape != (B, self.n_cells, 2):
            raise ValueError(
                f"counts must have shape [B, {self.n_cells}, 2] = {[B, self.n_cells, 2]}, got {tuple(counts.shape)}"
            )
        if counts.dtype.is_floating_point or counts.dtype == torch.bool or counts.dtype.is_complex:
            raise ValueError(f"counts must be integers (the env's state_counts), got {counts.dtype}")
        if B == 0:
            return counts.to(torch.uint8), torch.zeros(0, self.n_positions, 2, dtype=self.position_dtype)
        low, high = (int(v) for v in torch.aminmax(counts))
        if low < 0 or high > MAX_COUNT:
            raise ValueError(f"counts must lie in [0, {MAX_COUNT}], got [{low}, {high}]")
        codes = counts.to(torch.uint8 if high <= U8_MAX else torch.int16)

        scale = self._pos_scale.to(state.device)
        # Contiguous first: elementwise ops on the strided slice take the slow scalar path.
        scaled = state[:, self.layout.positions].contiguous().view(B, self.n_positions, 2)
        cells = (scaled * scale).round_()
        low, high = torch.aminmax(cells.view(-1, 2), dim=0)
        grid_max = self._grid_max.to(state.device)
        if (low < 0).any() or (high > grid_max).any() or not torch.equal(cells / scale, scaled):
            raise ValueError(
                "state positions are not grid cells divided by pos_scale (width - 1, height - 1): "
                "is this a state of this map's env?"
            )
        if check_maps:
            rows = torch.linspace(0, B - 1, min(B, MAP_CHECKS), device=state.device).round().long()
            maps = self.clear_zones(self.decode_map(codes[rows]), cells[rows].long())
            if not torch.equal(maps, state[rows, : self.map_dim]):  # the maps
                raise ValueError(
                    "state maps are not the beliefs of counts (m(U), m(F) of each cell): are counts "
                    "and state from the same step and this map's sensor model (m_f, m_e)?"
                )
        return codes.contiguous(), cells.to(self.position_dtype)

    # ------------------------------------------------------------------------------------------ decoding
    def decode(
        self, codes: torch.Tensor, positions: torch.Tensor, out: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Decode ``codes`` and ``positions`` into the env's float32 state ``[B, state_dim]``, bit for bit.
        ``out`` may pass a contiguous buffer to reuse. For ``uint8`` codes the whole state is one gather
        from a single table."""
        B = codes.shape[0]
        if out is None:
            out = torch.empty(B, self.state_dim, dtype=torch.float32, device=codes.device)
        fast = codes.dtype == torch.uint8 and positions.dtype == torch.uint8 and _LITTLE_ENDIAN
        if not (fast and codes.is_contiguous() and positions.is_contiguous() and out.is_contiguous()):
            self.decode_map(codes, out=out[:, : self.map_dim])
            scale = self._pos_scale.to(codes.device)
            torch.div(
                positions.to(torch.float32),
                scale,
                out=out[:, self.layout.positions].view(B, self.n_positions, 2),
            )
            return self.clear_zones(out, positions)
        if B == 0:
            return out
        table, offsets = self._state_table(codes.device)
        unknown, full, where = self.layout.unknown, self.layout.full, self.layout.positions
        index = self._index_buffer(B, codes.device)
        # The byte pair (positive, negative) read as one uint16: positive + 256 * negative.
        index[:, unknown].copy_(codes.view(torch.uint16).squeeze(-1))
        torch.add(index[:, unknown], (U8_MAX + 1) ** 2, out=index[:, full])  # the m(F) half of the table
        torch.add(positions.view(B, -1), offsets, out=index[:, where])
        torch.index_select(table, 0, index.view(-1), out=out.view(-1))
        return self.clear_zones(out, positions)

    def clear_zones(self, out: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
        """Zero m(U) and m(F) of each state's no-fly cells in ``out`` in place when ``no_fly_prior=known``."""
        if not self.known_zones or positions.shape[0] == 0 or self._zone_slots.start == self._zone_slots.stop:
            return out
        zones = positions[:, self._zone_slots].long()
        cell = zones[..., 0] * self.layout.height + zones[..., 1]  # [B, Z]
        out.scatter_(1, cell + self.layout.unknown.start, 0.0)
        out.scatter_(1, cell + self.layout.full.start, 0.0)
        return out

    def _state_table(self, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
        """Return the one-gather table ``[m(U) (65536), m(F) (65536), x / scale_x (256), y / scale_y (256)]``
        and the position offsets into it."""
        key = (str(device), "state")
        if key not in self._tables:
            with torch.inference_mode(False):  # cached: must not become an inference tensor
                self._build_state_table(device, key)
        return self._tables[key], self._tables[(str(device), "offsets")]

    def _build_state_table(self, device: torch.device, key: tuple) -> None:
        maps = self._table(device, U8_MAX + 1, U8_MAX + 1).reshape(-1)
        scale = self._pos_scale.to(device)
        cells = torch.arange(U8_MAX + 1, dtype=torch.float32, device=device)
        positions = (cells.unsqueeze(0) / scale.unsqueeze(1)).reshape(-1)  # the env's division
        self._tables[key] = torch.cat([maps, positions])
        axis = torch.arange(2, device=device, dtype=torch.int32) * (U8_MAX + 1)
        self._tables[(str(device), "offsets")] = (maps.numel() + axis).repeat(self.n_positions)

    def _index_buffer(self, rows: int, device: torch.device) -> torch.Tensor:
        """Return a reused int32 ``[rows, state_dim]`` buffer, so pages are not faulted in per call."""
        buffer = self._index
        if buffer is None or buffer.device != device or buffer.shape[0] < rows:
            with torch.inference_mode(False):  # reused: must not become an inference tensor
                buffer = self._index = torch.empty(rows, self.state_dim, dtype=torch.int32, device=device)
        return buffer[:rows]

    def decode_map(self, codes: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
        """Return the maps ``[B, 2 * cells]`` of ``codes [B, cells, 2]``."""
        B, C = codes.shape[0], self.n_cells
        if codes.shape[1:] != (C, 2):
            raise ValueError(f"codes must have shape [B, {C}, 2], got {tuple(codes.shape)}")
        if out is None:
            out = torch.empty(B, 2 * C, dtype=torch.float32, device=codes.device)
        if B == 0:
            return out
        if codes.dtype == torch.uint8:
            table = self._table(codes.device, U8_MAX + 1, U8_MAX + 1)
            if _LITTLE_ENDIAN and codes.is_contiguous():
                # The two bytes (positive, negative) read as one int16: positive + 256 * negative.
                index = codes.view(torch.int16).squeeze(-1).to(torch.int32).bitwise_and_(0xFFFF)
            else:
                index = codes[..., 0].to(torch.int32) + codes[..., 1].to(torch.int32) * (U8_MAX + 1)
        else:
            positive, negative = codes[..., 0].to(torch.int32), codes[..., 1].to(torch.int32)
            # Power-of-two table sizes (>= 256): few distinct tables however the maxima vary.
            rows, cols = (max(U8_MAX + 1, 1 << int(t.max()).bit_length()) for t in (positive, negative))
            if rows * cols > MAX_TABLE_ENTRIES:
                _, full, unknown = belief_masses(positive, negative, self.config.m_f, self.config.m_e)
                out[:, self.layout.unknown] = unknown
                out[:, self.layout.full] = full
                return out
            table = self._table(codes.device, rows, cols)
            index = positive.add_(negative.mul_(rows))
        index = index.view(-1)
        out[:, self.layout.unknown] = torch.index_select(table[0], 0, index).view(B, C)
        out[:, self.layout.full] = torch.index_select(table[1], 0, index).view(B, C)
        return out

    def _table(self, device: torch.device, rows: int, cols: int) -> torch.Tensor:
        """``[2, rows * cols]``: (m(U), m(F)) of the count pair (p, n) at ``p + rows * n``."""
        key = (str(device), rows, cols)
        table = self._tables.get(key)
        if table is None:
            with torch.inference_mode(False):  # cached: must not become an inference tensor
                table = self._tables[key] = self._pair_table(device, rows, cols)
        return table

    def _pair_table(self, device: torch.device, rows: int, cols: int) -> torch.Tensor:
        positive = torch.arange(rows, device=device).repeat(cols)
        negative = torch.arange(cols, device=device).repeat_interleave(rows)
        _, full, unknown = belief_masses(positive, negative, self.config.m_f, self.config.m_e)
        return torch.stack([unknown, full]).contiguous()

    def nbytes(self) -> int:
        """Bytes of the cached decode tables and index buffer."""
        tensors = [*self._tables.values(), *([self._index] if self._index is not None else [])]
        return sum(t.numel() * t.element_size() for t in tensors)
