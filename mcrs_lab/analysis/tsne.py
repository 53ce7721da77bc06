"""Paper figure 9: t-SNE of states from a real episodic buffer, coloured by their return H.

The same states (drawn from one run's saved D_E) are shown four ways: the raw state, EMC's random
projection, the keys of a trained SEMU embedding (FC) and of a trained CNN-SEMU embedding. Every panel
is also scored by *return locality*: the mean |H_i - H_j| over each point's 10 nearest neighbours
divided by the same over random pairs, in the representation itself and in the t-SNE plane. Below 1
means that nearby states have similar returns (the paper's "clusters by return"); 1 means no relation.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from mcrs.env.config import from_mapping
from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.training.episodic import build_embedding
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


def sample_memory(run: TrainingRun, n: int, seed: int = 0) -> MemorySample:
    """``n`` distinct entries of the run's saved buffer (all of them when it holds fewer)."""
    state = _episodic_state(run)
    memory = state["memory"]
    size = int(memory["size"])
    if size == 0:
        raise ValueError(f"{run.path}: the saved episodic memory is empty")
    generator = torch.Generator().manual_seed(seed)
    rows = torch.randperm(size, generator=generator)[: min(n, size)].sort().values
    codec = StateCodec(from_mapping(run.config["env"]))
    states = codec.decode(memory["codes"][rows], memory["positions"][rows])
    time = memory["step"][rows].to(torch.float32) / int(run.config["env"]["max_steps"])
    return MemorySample(run, states, time, memory["returns"][rows].clone())


def trained_embedding_keys(run: TrainingRun, sample: MemorySample) -> torch.Tensor:
    """Keys of ``sample``'s states under the embedding that ``run`` trained (loaded from its last.pt)."""
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

    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 4.2), squeeze=False)
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
