"""Shared by the training tests: compose the real Hydra config in-process, at a tiny size, or start
``mcrs-train`` as a user would."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

from mcrs.train import CONFIG_DIR

TINY = [
    "env.max_steps=10",
    "train.num_envs=4",
    "train.batch_episodes=4",
    "train.replay_episodes=20",
    "train.total_env_steps=200",
    "train.eval_interval=120",  # 3 batches: a command line's intervals are whole batches (evals at 0, 120, 200)
    "train.eval_episodes=2",
    "train.checkpoint_interval=100",
    "train.eps_anneal_steps=100",
    "train.target_update_episodes=8",
    "model.hidden_dim=16",
    "algo.mixing_embed_dim=8",
    "algo.hypernet_embed=16",
    "logger.progress_bar=false",
    "logger.log_interval=40",
    "threads=1",
]


#: Memory settings that fit the tiny runs (a small buffer, phi trained twice in 200 env steps).
TINY_MEMORY = [
    "algo.memory.capacity=500",
    "algo.memory.embedding_interval=80",
    "algo.memory.embedding_samples=64",
    "algo.memory.embedding_batch=32",
    "algo.memory.hidden_dim=16",
    "algo.memory.cnn_channels=[2,4,4]",
]


def compose_config(*overrides: str, tiny: bool = True, algo: str = "qmix") -> DictConfig:
    """The config of ``overrides``; ``algo`` is used unless an override picks one (the suite's default is
    QMIX, the cheapest; ``mcrs-train``'s own default is CNN-SEMU)."""
    chosen = [] if any(o.startswith("algo=") for o in overrides) else [f"algo={algo}"]
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return compose(config_name="config", overrides=[*chosen, *(TINY if tiny else []), *overrides])


def start_train(*args: str, cwd: Path, **popen) -> subprocess.Popen:
    """``python -m mcrs.train *args`` in ``cwd`` with piped text output (Hydra's short errors)."""
    return subprocess.Popen(
        [sys.executable, "-m", "mcrs.train", *args],
        cwd=cwd,
        env={**os.environ, "HYDRA_FULL_ERROR": "0"},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **popen,
    )
