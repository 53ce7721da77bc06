"""State embeddings phi, the keys of the episodic buffer D_E (paper section 5, eq. 31).

The paper's three memories differ only here:

- :class:`RandomProjection` (EMC): a fixed Gaussian projection of the flat state, never trained.
- :class:`FCEmbedding` (SEMU, EMU's dCAE): a fully connected encoder-decoder conditioned on t/T.
- :class:`CNNEmbedding` (CNN-SEMU, figure 3d/3f): a CNN over the map part of the state, and a fully
  connected layer over the positions and t/T.

Every embedding maps ``state [*B, D]`` and ``time [*B]`` (t/T) to keys ``[*B, key_dim]``. The trainable
ones also decode, ``reconstruct(keys, time) -> (state_hat [*B, D], return_hat [*B])``, and are trained by
:class:`~mcrs.models.embedding_training.EmbeddingTrainer` on eq. 31. The state starts with the maps as an
image ``[2, width, height]`` (:class:`mcrs.env.layout.MapImage`). Parameters are drawn from ``seed`` inside
:func:`torch.random.fork_rng`, so one seed gives one embedding and the global RNG is untouched."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import nn
from torch.nn import functional as F

from mcrs.choices import EMBEDDINGS
from mcrs.env.layout import MapImage

Kernel = int | tuple[int, int]


# ------------------------------------------------------------------------------------------------ helpers
def positive_int(name: str, value: Any) -> int:
    """Return ``value`` if it is a positive int, else raise a ValueError naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ValueError(f"{name} must be a positive int, got {value!r}")
    return value


def _flatten_inputs(state: torch.Tensor, time: torch.Tensor | float | None, state_dim: int):
    """Check the state's last dimension and flatten the leading batch shape (time broadcast onto it)."""
    if state.dim() == 0 or state.shape[-1] != state_dim:
        raise ValueError(
            f"state must have shape [..., {state_dim}] (the embedding's state_dim), got {tuple(state.shape)}"
        )
    lead = state.shape[:-1]
    flat = state.reshape(-1, state_dim)
    if time is None:
        return lead, flat, None
    time = torch.as_tensor(time, dtype=state.dtype, device=state.device)
    try:
        time = time.expand(lead)
    except RuntimeError as err:
        raise ValueError(
            f"time must have the state's leading shape {tuple(lead)} (one t/T per state), got {tuple(time.shape)}"
        ) from err
    return lead, flat, time.reshape(-1)


def _linear_with_time(layer: nn.Linear, x: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
    """Compute ``layer(cat([x, time[:, None]], -1))`` without copying every state into a concatenation."""
    weight = layer.weight
    out = F.linear(x, weight[:, :-1], layer.bias)
    return out + time.unsqueeze(-1) * weight[:, -1]


def _pair(name: str, value: Kernel) -> tuple[int, int]:
    pair = (value, value) if isinstance(value, int) and not isinstance(value, bool) else tuple(value)
    if len(pair) != 2 or any(isinstance(v, bool) or not isinstance(v, int) or v <= 0 for v in pair):
        raise ValueError(f"{name} must be a positive int or a pair of them, got {value!r}")
    return pair  # type: ignore[return-value]


def conv_output_size(size: int, kernel: int, stride: int, padding: int) -> int:
    """Output length of a convolution along one axis (PyTorch's formula)."""
    return (size + 2 * padding - kernel) // stride + 1


def default_cnn_kernels(map_shape: tuple[int, int], layers: int = 3) -> list[tuple[int, int]]:
    """Return figure 3f's layers for any map: 3x3 stride-2 layers, then one kernel the size of the remaining
    map. 20x20 -> 10 -> 5 -> 5x5 kernel (the paper's); 10x10 -> 5 -> 3 -> 3x3; 15x15 -> 8 -> 4 -> 4x4."""
    size_x, size_y = map_shape
    for _ in range(layers - 1):
        size_x, size_y = conv_output_size(size_x, 3, 2, 1), conv_output_size(size_y, 3, 2, 1)
    return [(3, 3)] * (layers - 1) + [(size_x, size_y)]


# ----------------------------------------------------------------------------------------------- modules
class StateEmbedding(nn.Module):
    """Base class: ``forward(state [*B, D], time [*B]) -> keys [*B, key_dim]`` for any leading shape ``*B``."""

    trainable: bool = True
    # On CPU without autograd, batches are encoded this many states at a time so the activations stay in
    # cache (docs/PERFORMANCE.md, "Figures behind constants"). GPUs take the batch in one pass.
    inference_chunk: int = 1024

    def __init__(self, state_dim: int, key_dim: int) -> None:
        super().__init__()
        self.state_dim = positive_int("state_dim", state_dim)
        self.key_dim = positive_int("key_dim", key_dim)

    def forward(self, state: torch.Tensor, time: torch.Tensor | float) -> torch.Tensor:
        lead, flat, flat_time = _flatten_inputs(state, time, self.state_dim)
        return self._encode_chunked(flat, flat_time).reshape(*lead, self.key_dim)

    def _encode_chunked(self, state: torch.Tensor, time: torch.Tensor | None) -> torch.Tensor:
        n, chunk = state.shape[0], self.inference_chunk
        if torch.is_grad_enabled() or n <= chunk or state.device.type != "cpu":
            return self.encode(state, time)
        keys = state.new_empty(n, self.key_dim)
        workspace = self.workspace(chunk, state)
        for i in range(0, n, chunk):
            chunk_time = None if time is None else time[i : i + chunk]
            keys[i : i + chunk] = self.encode(state[i : i + chunk], chunk_time, workspace)
        return keys

    def workspace(self, rows: int, like: torch.Tensor) -> torch.Tensor | None:
        """Return scratch memory reused by every chunk of a chunked pass, or None."""
        return None

    def encode(
        self, state: torch.Tensor, time: torch.Tensor | None, workspace: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Return keys ``[N, key_dim]`` of a checked flat batch; ``workspace`` is given only in chunked
        inference passes."""
        raise NotImplementedError

    def reconstruct(
        self, keys: torch.Tensor, time: torch.Tensor | float
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Decode keys into ``(state_hat [*B, D], return_hat [*B])``; only trainable embeddings have a decoder."""
        raise TypeError(f"{type(self).__name__} has no decoder: it is not trained")


class RandomProjection(StateEmbedding):
    """EMC's key ``x = s @ P``, with ``P [D, key_dim]`` drawn once from N(0, 1/key_dim). This is EMC's
    ``rng.normal(0, 1/sqrt(latent_dim), ...)``. ``P`` is a buffer, never trained; the time is ignored."""

    trainable = False

    def __init__(self, state_dim: int, key_dim: int = 4, seed: int = 0) -> None:
        super().__init__(state_dim, key_dim)
        generator = torch.Generator().manual_seed(seed)
        projection = torch.randn(state_dim, key_dim, generator=generator) / math.sqrt(key_dim)
        self.register_buffer("projection", projection)

    def encode(
        self, state: torch.Tensor, time: torch.Tensor | None, workspace: torch.Tensor | None = None
    ) -> torch.Tensor:
        return state @ self.projection

    def forward(self, state: torch.Tensor, time: torch.Tensor | float | None = None) -> torch.Tensor:
        lead, flat, _ = _flatten_inputs(state, None, self.state_dim)
        return self._encode_chunked(flat, None).reshape(*lead, self.key_dim)


class Decoder(nn.Module):
    """EMU's dCAE decoder: ``[x, t/T] -> hidden -> hidden`` then two heads, the state (D) and the return (1)."""

    def __init__(self, key_dim: int, state_dim: int, hidden_dim: int) -> None:
        super().__init__()
        self.input = nn.Linear(key_dim + 1, hidden_dim)
        self.hidden = nn.Linear(hidden_dim, hidden_dim)
        self.state_head = nn.Linear(hidden_dim, state_dim)
        self.return_head = nn.Linear(hidden_dim, 1)

    def forward(self, keys: torch.Tensor, time: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = F.relu(_linear_with_time(self.input, keys, time))
        h = F.relu(self.hidden(h))
        return self.state_head(h), self.return_head(h).squeeze(-1)


class _EncoderDecoder(StateEmbedding):
    """A trainable embedding: a subclass's encoder plus the shared :class:`Decoder`."""

    def __init__(self, state_dim: int, key_dim: int, hidden_dim: int) -> None:
        super().__init__(state_dim, key_dim)
        self.hidden_dim = positive_int("hidden_dim", hidden_dim)
        self.decoder = Decoder(key_dim, state_dim, hidden_dim)

    def reconstruct(
        self, keys: torch.Tensor, time: torch.Tensor | float
    ) -> tuple[torch.Tensor, torch.Tensor]:
        lead, flat_keys, flat_time = _flatten_inputs(keys, time, self.key_dim)
        state_hat, return_hat = self.decoder(flat_keys, flat_time)
        return state_hat.reshape(*lead, self.state_dim), return_hat.reshape(lead)


class FCEmbedding(_EncoderDecoder):
    """SEMU / EMU's dCAE encoder: ``[s, t/T] -> hidden -> hidden -> key_dim`` (ReLU between hidden layers)."""

    def __init__(self, state_dim: int, key_dim: int = 4, hidden_dim: int = 64) -> None:
        super().__init__(state_dim, key_dim, hidden_dim)
        self.input = nn.Linear(state_dim + 1, hidden_dim)
        self.hidden = nn.Linear(hidden_dim, hidden_dim)
        self.output = nn.Linear(hidden_dim, key_dim)

    def encode(
        self, state: torch.Tensor, time: torch.Tensor, workspace: torch.Tensor | None = None
    ) -> torch.Tensor:
        h = F.relu(_linear_with_time(self.input, state, time))
        h = F.relu(self.hidden(h))
        return self.output(h)


class CNNEmbedding(_EncoderDecoder):
    """CNN-SEMU's encoder (paper figure 3d, 3f): a CNN on the map and a fully connected layer on the rest.

    The map image ``[2, width, height]`` goes through 3x3 stride-2 padded convolutions, then an unpadded
    one whose kernel covers the remaining map, each followed by a ReLU. The positions and t/T go through
    ``Linear(rest + 1, hidden) -> ReLU``. The two feature vectors are concatenated and mapped linearly to
    the key."""

    def __init__(
        self,
        state_dim: int,
        map_shape: Sequence[int],
        key_dim: int = 4,
        hidden_dim: int = 64,
        channels: Sequence[int] = (8, 16, 32),
        kernels: Sequence[Kernel] | None = None,
    ) -> None:
        super().__init__(state_dim, key_dim, hidden_dim)
        self.map_shape = _check_map_shape(map_shape, state_dim)
        channels = tuple(channels)
        if not channels or any(isinstance(c, bool) or not isinstance(c, int) or c <= 0 for c in channels):
            raise ValueError(f"channels must be a non-empty list of positive ints, got {channels!r}")
        if kernels is None:
            kernel_pairs = default_cnn_kernels(self.map_shape, len(channels))
        else:
            kernel_pairs = [_pair("kernels", k) for k in kernels]
            if len(kernel_pairs) != len(channels):
                raise ValueError(
                    f"kernels must give one kernel per conv layer ({len(channels)} channels), got {len(kernel_pairs)}"
                )
        self.map_image = MapImage(*self.map_shape)
        self.map_cells = self.map_image.dim
        self.rest_dim = state_dim - self.map_cells

        convs, size, in_channels = [], self.map_shape, self.map_image.channels
        for i, (out_channels, kernel) in enumerate(zip(channels, kernel_pairs, strict=True)):
            last = i == len(channels) - 1
            stride, padding = (1, 0) if last else (2, 1)
            size = tuple(conv_output_size(n, k, stride, padding) for n, k in zip(size, kernel, strict=True))
            if min(size) <= 0:
                raise ValueError(
                    f"kernels {kernel_pairs} do not fit the {self.map_shape} map (map_shape): "
                    f"layer {i} has no output position"
                )
            convs.append(nn.Conv2d(in_channels, out_channels, kernel, stride=stride, padding=padding))
            in_channels = out_channels
        if size != (1, 1):
            raise ValueError(
                f"kernels {kernel_pairs} reduce the {self.map_shape} map (map_shape) to {size}, not 1x1: "
                f"the last layer must cover the whole remaining map (default kernels do)"
            )
        self.kernels = kernel_pairs
        self.convs = nn.ModuleList(convs)
        self.rest = nn.Linear(self.rest_dim + 1, hidden_dim)
        self.output = nn.Linear(channels[-1] + hidden_dim, key_dim)

    def workspace(self, rows: int, like: torch.Tensor) -> torch.Tensor:
        """Return a channels-last image ``[rows, width, height, 2]`` reused by every chunk; fresh ones cost
        more page faults than the convolutions on 2 cores."""
        return like.new_empty(rows, *self.map_shape, 2)

    def map_features(self, state: torch.Tensor, workspace: torch.Tensor | None = None) -> torch.Tensor:
        """Return CNN features ``[N, channels[-1]]`` of the maps of ``state [N, D]``, laid out channels-last
        for oneDNN on CPU."""
        image = self.map_image.image(state)
        if workspace is None:
            h = image.contiguous(memory_format=torch.channels_last)
        else:
            h = workspace[: state.shape[0]].permute(0, 3, 1, 2)
            h.copy_(image)
        for conv in self.convs[:-1]:
            h = F.relu(conv(h), inplace=True)
        # The last layer has one output position: a matrix product with the flattened kernel is the same
        # convolution and avoids the conv kernel's overhead for a 1x1 output. Both sides are flattened in
        # (height, width, channel) order, a view of the channels-last activations.
        last = self.convs[-1]
        weight = last.weight.permute(0, 2, 3, 1).flatten(1)
        return F.relu(F.linear(h.permute(0, 2, 3, 1).flatten(1), weight, last.bias))

    def encode(
        self, state: torch.Tensor, time: torch.Tensor, workspace: torch.Tensor | None = None
    ) -> torch.Tensor:
        rest = F.relu(_linear_with_time(self.rest, self.map_image.rest(state), time))
        return self.output(torch.cat([self.map_features(state, workspace), rest], dim=-1))


def _check_map_shape(map_shape: Sequence[int] | None, state_dim: int) -> tuple[int, int]:
    if map_shape is None:
        raise ValueError("map_shape (width, height) is required for the cnn embedding")
    shape = tuple(map_shape)
    if len(shape) != 2 or any(isinstance(v, bool) or not isinstance(v, int) or v <= 0 for v in shape):
        raise ValueError(f"map_shape must be two positive ints (width, height), got {map_shape!r}")
    maps = MapImage(*shape)
    if maps.dim > state_dim:
        raise ValueError(
            f"map_shape {shape} does not fit the state: its {maps.channels} maps need {maps.dim} values, "
            f"more than state_dim = {state_dim}"
        )
    return shape  # type: ignore[return-value]


def make_embedding(
    kind: str,
    state_dim: int,
    map_shape: Sequence[int] | None = None,
    key_dim: int = 4,
    hidden_dim: int = 64,
    cnn_channels: Sequence[int] = (8, 16, 32),
    seed: int = 0,
) -> StateEmbedding:
    """Build the embedding ``kind`` ("random" EMC, "fc" SEMU, "cnn" CNN-SEMU) with parameters drawn from
    ``seed``."""
    if kind not in EMBEDDINGS:
        raise ValueError(f"kind must be one of {EMBEDDINGS}, got {kind!r}")
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ValueError(f"seed must be an int, got {seed!r}")
    if kind == "random":
        return RandomProjection(state_dim, key_dim, seed=seed)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        if kind == "fc":
            return FCEmbedding(state_dim, key_dim, hidden_dim)
        return CNNEmbedding(state_dim, map_shape, key_dim, hidden_dim, cnn_channels)  # type: ignore[arg-type]
