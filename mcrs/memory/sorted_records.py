"""The sorted record arrays behind :class:`~mcrs.memory.index.GridIndex`, and the array primitives they use.

They know nothing of the index's geometry. The helpers use numpy on CPU where it is faster than torch
(docs/PERFORMANCE.md, "Figures behind constants")."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch


def slot_bits_for(capacity: int) -> int:
    """Bits that hold a slot number below ``capacity``."""
    return max(1, (capacity - 1).bit_length())


def float_order(x: torch.Tensor) -> torch.Tensor:
    """An int64 in ``[0, 2^32)`` per float32 of ``x`` that orders like the floats (-0.0 counts as 0.0)."""
    bits = (x.to(torch.float32) + 0.0).view(torch.int32).to(torch.int64)  # + 0.0: -0.0 becomes 0.0
    return torch.where(bits >= 0, bits + 2**31, 2**31 - 1 - (bits & 0x7FFFFFFF))


def flatnonzero(mask: torch.Tensor) -> torch.Tensor:
    """Return the indices ``[k]`` of the True elements of a 1-D ``mask``; numpy on CPU is about 10x faster."""
    if mask.device.type == "cpu":
        return torch.from_numpy(np.flatnonzero(mask.numpy()))
    return mask.nonzero().squeeze(1)


def repeat(values: torch.Tensor, counts: torch.Tensor, total: int) -> torch.Tensor:
    """Repeat ``values[i]`` ``counts[i]`` times, ``total`` in all; numpy on CPU is about 2x faster."""
    if values.device.type == "cpu":
        return torch.from_numpy(np.repeat(values.numpy(), counts.numpy()))
    return torch.repeat_interleave(values, counts, output_size=total)


def search_sorted(sequence: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """``torch.searchsorted(sequence, values)`` (left); numpy's on the CPU, faster for sorted values."""
    if sequence.device.type == "cpu":
        return torch.from_numpy(np.searchsorted(sequence.numpy(), values.numpy()))
    return torch.searchsorted(sequence, values)


class Records(NamedTuple):
    """Index records sorted by int64 ``order``, with their int32 ``slot`` and the standardised key copy
    ``coords [d, n]``."""

    order: torch.Tensor
    slot: torch.Tensor
    coords: torch.Tensor

    def prefix(self, n: int) -> Records:
        return Records(self.order[:n], self.slot[:n], self.coords[:, :n])


def merge_records(a: Records, b: Records, out: Records | None = None) -> Records:
    """Merge the few sorted records ``b`` into the many ``a`` with one masked copy per array; ``out`` may
    provide the memory."""
    total = a.order.numel() + b.order.numel()
    if out is None:
        out = Records(
            a.order.new_empty(total), a.slot.new_empty(total), a.coords.new_empty((len(a.coords), total))
        )
    out = out.prefix(total)
    # Where b's records go (after a's records of equal key), and the mask of a's.
    position = torch.searchsorted(a.order, b.order, right=True) + torch.arange(
        b.order.numel(), device=a.order.device
    )
    keep = torch.ones(total, dtype=torch.bool, device=a.order.device)
    keep[position] = False
    for source, extra, target in zip(a, b, out, strict=True):
        _merge_into(source, extra, target, keep, position)
    return out


def _merge_into(
    a: torch.Tensor, b: torch.Tensor, out: torch.Tensor, keep: torch.Tensor, position: torch.Tensor
) -> None:
    """``out[..., keep] = a`` and ``out[..., position] = b`` (along the last dimension)."""
    if a.device.type == "cpu":  # numpy's boolean-mask copy is one pass, torch's CPU one much slower
        # (docs/PERFORMANCE.md, "Figures behind constants")
        target = out.numpy()
        target[..., keep.numpy()] = a.numpy()
        target[..., position.numpy()] = b.numpy()
        return
    out[..., keep] = a
    out[..., position] = b


def unique_pairs(
    parts: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]], bits: int, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Concatenate (query, slot, d2) parts sorted by query then slot, each pair once; a stale and a current
    record may both find a slot."""
    if not parts:
        empty = torch.zeros(0, dtype=torch.int64, device=device)
        return empty, empty, torch.zeros(0, dtype=torch.float32, device=device)
    query, slot, d2 = (torch.cat(x) for x in zip(*parts, strict=True))
    pair, order = torch.sort((query << bits) | slot)
    first = torch.ones_like(pair, dtype=torch.bool)
    first[1:] = pair[1:] != pair[:-1]
    order = order[first]
    return query[order], slot[order], d2[order]
