"""Helpers shared by the benchmark commands: process settings, the real training config, synthetic episodes.

The harness around every command (arguments, machine facts, JSON results) is :mod:`mcrs_benchmarks.harness`.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

import torch
from omegaconf import DictConfig
from tensordict import TensorDict

from mcrs.env.config import EnvConfig
from mcrs.env.core import N_ACTIONS

# --quick: tiny episodes and batches, for a smoke test of a whole command in seconds.
QUICK_OVERRIDES = (
    "env.max_steps=6",
    "train.batch_episodes=4",
    "train.num_envs=4",
    "train.replay_episodes=16",
    "train.eval_episodes=2",
)


def load_average() -> str:
    """The 1-minute load average: other processes on the machine skew every figure, so show it."""
    try:
        return f"{os.getloadavg()[0]:.2f}"
    except OSError:
        return "n/a"


def pass_fail(ok: bool) -> str:
    return "PASS" if ok else "FAIL"


@contextmanager
def benchmark_process(threads: int) -> Iterator[None]:
    """Run a benchmark with ``threads`` torch threads (0: torch's default) and without TorchRL's INFO lines
    (storage allocations would break the tables); restore both after, since tests call ``main`` in-process."""
    previous_threads = torch.get_num_threads()
    torchrl_log = logging.getLogger("torchrl")
    previous_level = torchrl_log.level
    torchrl_log.setLevel(logging.WARNING)
    if threads:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous_threads)
        torchrl_log.setLevel(previous_level)


def compose_config(map_name: str, quick: bool, extra: Sequence[str] = (), algo: str = "qmix") -> DictConfig:
    """The real ``mcrs-train`` config (pymarl preset, ``algo``) for ``map_name``, composed in-process."""
    from hydra import compose, initialize_config_dir

    from mcrs.train import CONFIG_DIR  # also registers the structured config schema

    overrides = [
        f"env={map_name}",
        "preset=pymarl",
        f"algo={algo}",
        *(QUICK_OVERRIDES if quick else ()),
        *extra,
    ]
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return compose(config_name="config", overrides=overrides)


def synthetic_episodes(n: int, env_config: EnvConfig, generator: torch.Generator) -> TensorDict:
    """``n`` valid episodes in the episode layout ``[n, T + 1]`` read by ``ValueFactorisationLoss``.

    Every step allows at least one action and every action taken is allowed; each episode ends at step T
    (``done``), and about a quarter end in a terminal state (no bootstrap), so that the agreement check
    also covers the ``terminated`` branch (our environment itself only truncates).
    """
    T, N, A = env_config.max_steps, env_config.n_uavs, N_ACTIONS
    shape = (n, T + 1)
    mask = torch.rand(*shape, N, A, generator=generator) < 0.6
    forced = torch.randint(A, (*shape, N, 1), generator=generator)
    mask.scatter_(-1, forced, True)
    noise = torch.rand(*shape, N, A, generator=generator).masked_fill(~mask, -1.0)
    action = noise.argmax(-1)
    action[:, -1] = 0  # padding row, as episodes_from_rollout writes it
    reward = torch.randn(*shape, 1, generator=generator)
    reward[:, -1] = 0.0
    done = torch.zeros(*shape, 1, dtype=torch.bool)
    done[:, T - 1 :] = True
    terminated = torch.zeros(*shape, 1, dtype=torch.bool)
    terminated[:, T - 1, 0] = torch.rand(n, generator=generator) < 0.25
    filled = torch.ones(*shape, dtype=torch.bool)
    filled[:, -1] = False
    out = TensorDict(batch_size=list(shape))
    out.set(("agents", "observation"), torch.rand(*shape, N, env_config.obs_dim, generator=generator))
    out.set(("agents", "action_mask"), mask)
    out.set("state", torch.rand(*shape, env_config.state_dim, generator=generator))
    out.set(("agents", "action"), action)
    out.set("reward", reward)
    out.set("done", done)
    out.set("terminated", terminated)
    out.set("filled", filled)
    return out
