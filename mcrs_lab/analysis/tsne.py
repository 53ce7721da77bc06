"""Paper figure 9: t-SNE of states from a real episodic buffer, coloured by their return H.

The same states (drawn from one run's saved D_E) are shown four ways: the raw state, EMC's random
projection, the keys of a trained SEMU embedding (FC) and of a trained CNN-SEMU embedding. Every panel
is also scored by *return locality*: the mean |H_i - H_j| over each point's 10 nearest neighbours
divided by the same over random pairs, in the representation itself and in the t-SNE plane. Below 1
means that nearby states have similar returns (the paper's "clusters by return"); 1 means no relation.

A campaign keeps the figure as two records (mcrs_lab.campaign.figure9), each an ``.npz`` of plain arrays
and a JSON ``meta`` string, read without pickles: the sampled states (:data:`STATES_FORMAT`: their
compact codes, time and H, drawn before the run's memory is pruned) and the t-SNE
(:data:`TSNE_FORMAT`: each panel's 2-D points, H and the scores), from which ``mcrs-report`` draws the
figure alone.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import OmegaConf

from mcrs.env.config import from_mapping
from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.training.episodic import build_embedding
from mcrs.experiment.util.atomic import write_bytes_atomic
from mcrs.memory.codec import StateCodec
from mcrs.models.embeddings import make_embedding
from mcrs_lab.analysis.runs import TrainingRun

NEIGHBOURS = 10


@dataclass(frozen=True)
class MemorySample:
    """States drawn from a run's D_E: ``state [n, D]``, ``time [n]`` (t/T), ``returns [n]`` (H)."""

    run: TrainingRun
    state: torch.Tensor
    time: torch.Tensor
    returns: torch.Tensor


def _episodic_state(run: TrainingRun) -> dict:
    path = ckpt.checkpoint_path(run.path)
    payload = ckpt.refuse_pre_release(ckpt.load(path, mmap=True), path)
    if "callbacks" in payload:  # mapped, then used: checked against the file's checksum
        ckpt.verify(payload, path, ["callbacks"])
    if "memory" not in payload.get("callbacks", {}):
        raise ValueError(f"{run.path}: its last.pt holds no episodic memory (algo {run.algo_name})")
    return payload["callbacks"]["memory"]


def sample_codes(run: TrainingRun, n: int, seed: int = 0) -> dict[str, Any]:
    """``n`` distinct entries of the run's saved buffer as stored (all of them when it holds fewer):
    ``codes``, ``positions``, ``step``, ``returns`` (H) and the buffer's ``size``."""
    state = _episodic_state(run)
    memory = state.get("memory")
    if memory is None:
        raise ValueError(f"{run.path}: its last.pt holds no episodic memory entries (pruned)")
    size = int(memory["size"])
    if size == 0:
        raise ValueError(f"{run.path}: the saved episodic memory is empty")
    generator = torch.Generator().manual_seed(seed)
    rows = torch.randperm(size, generator=generator)[: min(n, size)].sort().values
    return {
        "codes": memory["codes"][rows].clone(),
        "positions": memory["positions"][rows].clone(),
        "step": memory["step"][rows].clone(),
        "returns": memory["returns"][rows].to(torch.float32).clone(),
        "size": size,
    }


def decode_sample(run: TrainingRun, codes: dict[str, Any], env: dict[str, Any] | None = None) -> MemorySample:
    """The float32 states, t/T and H of :func:`sample_codes`' entries (``env``: the map's config, default
    the run's)."""
    env = env or run.config["env"]
    codec = StateCodec(from_mapping(env))
    states = codec.decode(torch.as_tensor(codes["codes"]), torch.as_tensor(codes["positions"]))
    time = torch.as_tensor(codes["step"]).to(torch.float32) / int(env["max_steps"])
    return MemorySample(run, states, time, torch.as_tensor(codes["returns"]).to(torch.float32))


def sample_memory(run: TrainingRun, n: int, seed: int = 0) -> MemorySample:
    """``n`` distinct entries of the run's saved buffer (all of them when it holds fewer)."""
    return decode_sample(run, sample_codes(run, n, seed))


def trained_embedding_keys(run: TrainingRun, sample: MemorySample) -> torch.Tensor:
    """Keys of ``sample``'s states under the embedding that ``run`` trained (loaded from its last.pt; a
    pruned one keeps it)."""
    cfg = OmegaConf.create(run.config)
    embedding = build_embedding(cfg, from_mapping(run.config["env"]))
    embedding.load_state_dict(_episodic_state(run)["embedding"])
    with torch.no_grad():
        return embedding(sample.state, sample.time)


def random_projection_keys(sample: MemorySample, key_dim: int = 4, seed: int = 0) -> torch.Tensor:
    """EMC's key of the states: a fixed Gaussian projection."""
    projection = make_embedding("random", sample.state.shape[-1], key_dim=key_dim, seed=seed)
    return projection(sample.state)


def return_locality(points: np.ndarray, returns: np.ndarray, seed: int = 0) -> float:
    """Mean |H_i - H_j| over the 10 nearest neighbours j of each point, over the same for random pairs."""
    from sklearn.neighbors import NearestNeighbors

    k = min(NEIGHBOURS, len(points) - 1)
    if k < 1:
        return float("nan")
    _, idx = NearestNeighbors(n_neighbors=k + 1).fit(points).kneighbors(points)
    near = np.abs(returns[:, None] - returns[idx[:, 1:]]).mean()
    rng = np.random.default_rng(seed)
    far = np.abs(returns - returns[rng.permutation(len(returns))]).mean()
    return float(near / far) if far > 0 else float("nan")


def standardise(x: np.ndarray) -> np.ndarray:
    return (x - x.mean(0)) / np.maximum(x.std(0), 1e-8)


def tsne_2d(features: np.ndarray, seed: int = 0) -> np.ndarray:
    """t-SNE (scikit-learn, Barnes-Hut, perplexity 30) of standardised features; wide inputs (raw states)
    go through PCA to 50 dimensions first, as is usual."""
    from sklearn.decomposition import PCA
    from sklearn.manifold import TSNE

    x = standardise(features.astype(np.float64))
    if x.shape[1] > 50:
        x = PCA(n_components=50, random_state=seed).fit_transform(x)
    perplexity = float(min(30.0, max(2.0, (len(x) - 1) / 3)))
    return TSNE(n_components=2, perplexity=perplexity, init="pca", random_state=seed).fit_transform(x)


def plot_tsne(
    panels: dict[str, np.ndarray], returns: np.ndarray, scores: dict[str, float], path: Path
) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(
        1, len(panels), figsize=(3.6 * len(panels) + 1.0, 3.9), squeeze=False, layout="constrained"
    )
    scatter = None
    for ax, (name, xy) in zip(axes[0], panels.items(), strict=True):
        scatter = ax.scatter(xy[:, 0], xy[:, 1], c=returns, s=1.5, cmap="viridis", rasterized=True)
        ax.set_title(f"{name}\nreturn locality {scores[name]:.2f}", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.colorbar(scatter, ax=axes[0].tolist(), shrink=0.8, label="H (return from the state)")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


# ----------------------------------------------------------------------------------------- records
STATES_FORMAT = "mcrs-tsne-states"
TSNE_FORMAT = "mcrs-tsne"
TSNE_VERSION = 1
#: The arrays of each record and their dtypes' kinds (u: unsigned, i: signed, f: float).
STATES_ARRAYS = {"codes": "ui", "positions": "ui", "step": "ui", "returns": "f"}
TSNE_ARRAYS = {"xy": "f", "returns": "f"}
MAX_RECORD_BYTES = 64 * 2**20


class TsneRecordError(ValueError):
    """A t-SNE record that cannot be read: one line naming the file and the field."""


def write_npz_record(path: Path, arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> Path:
    """``arrays`` and ``meta`` (JSON) into ``path``, compressed, atomically."""
    import io

    buffer = io.BytesIO()
    np.savez_compressed(buffer, meta=np.array(json.dumps(meta, sort_keys=True)), **arrays)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_bytes_atomic(path, buffer.getvalue())


def read_npz_record(path: Path, fmt: str) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """The arrays and meta of a record of format ``fmt`` (:data:`STATES_FORMAT` or :data:`TSNE_FORMAT`),
    checked: no pickles, the format and version, every array's dtype and length; else
    :class:`TsneRecordError`."""
    import zipfile

    expected = STATES_ARRAYS if fmt == STATES_FORMAT else TSNE_ARRAYS
    try:
        if path.stat().st_size > MAX_RECORD_BYTES:
            raise TsneRecordError(f"{path}: larger than {MAX_RECORD_BYTES >> 20} MiB: not a t-SNE record")
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as error:
        if isinstance(error, TsneRecordError):
            raise
        raise TsneRecordError(f"{path}: not a t-SNE record ({type(error).__name__}: {error})") from None
    try:
        meta = json.loads(str(arrays.pop("meta")))
    except (KeyError, ValueError):
        raise TsneRecordError(f"{path}: field meta: missing or not JSON") from None
    if not isinstance(meta, dict) or meta.get("format") != fmt:
        found = meta.get("format") if isinstance(meta, dict) else None
        raise TsneRecordError(f"{path}: field meta.format: {found!r}, expected {fmt!r}")
    if meta.get("version") != TSNE_VERSION:
        raise TsneRecordError(
            f"{path}: field meta.version: {meta.get('version')!r}; this mcrs reads {TSNE_VERSION}"
        )
    n = None
    for name, kinds in expected.items():
        array = arrays.get(name)
        if array is None or array.dtype.kind not in kinds:
            what = "missing" if array is None else f"dtype {array.dtype}"
            raise TsneRecordError(f"{path}: field {name}: {what}")
        length = (
            array.shape[1] if (fmt == TSNE_FORMAT and name == "xy") else (array.shape[0] if array.ndim else 0)
        )
        if n is not None and length != n:
            raise TsneRecordError(f"{path}: field {name}: {length} entries, not {n}")
        n = length
    if fmt == TSNE_FORMAT:
        _check_tsne(path, arrays, meta)
    return arrays, meta


def _check_tsne(path: Path, arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> None:
    xy, returns = arrays["xy"], arrays["returns"]
    panels = meta.get("panels")
    if xy.ndim != 3 or xy.shape[2] != 2 or xy.shape[1] < 2:
        raise TsneRecordError(f"{path}: field xy: shape {xy.shape}, expected [panels, n >= 2, 2]")
    if returns.ndim != 1 or not np.isfinite(returns).all() or not np.isfinite(xy).all():
        raise TsneRecordError(f"{path}: field returns or xy: not finite numbers")
    if not isinstance(panels, list) or len(panels) != xy.shape[0]:
        raise TsneRecordError(f"{path}: field meta.panels: a list of {xy.shape[0]} panels")
    for k, panel in enumerate(panels):
        ok = isinstance(panel, dict) and isinstance(panel.get("name"), str)
        if not ok or not all(
            isinstance(panel.get(f), (int, float)) for f in ("dims", "locality", "locality_tsne")
        ):
            raise TsneRecordError(f"{path}: field meta.panels[{k}]: name, dims, locality, locality_tsne")


def tsne_record(
    features: dict[str, torch.Tensor], returns: np.ndarray, seed: int
) -> tuple[dict[str, np.ndarray], list[dict[str, Any]]]:
    """The t-SNE record's arrays (``xy [panels, n, 2]``, ``returns``) and its panels (name, dims, return
    locality in the representation and in the plane), one panel per entry of ``features``."""
    panels, xys = [], []
    returns = returns.astype(np.float64)
    for name, x in features.items():
        x = x.numpy()
        print(f"t-SNE of {len(x)} states: {name} ...", flush=True)
        xy = tsne_2d(x, seed)
        xys.append(xy.astype(np.float32))
        panels.append(
            {
                "name": name,
                "dims": int(x.shape[1]),
                "locality": return_locality(standardise(x.astype(np.float64)), returns, seed),
                "locality_tsne": return_locality(xy, returns, seed),
            }
        )
    return {"xy": np.stack(xys), "returns": returns.astype(np.float32)}, panels


def tsne_table(panels: list[dict[str, Any]]) -> str:
    """The markdown table of a t-SNE's panels: dims and return locality."""
    from mcrs.experiment.util.tables import markdown

    rows = [[p["name"], str(p["dims"]), f"{p['locality']:.3f}", f"{p['locality_tsne']:.3f}"] for p in panels]
    return markdown(
        ["representation", "dims", "return locality (representation)", "return locality (t-SNE)"], rows
    )
