"""What a training run will hold in memory, estimated from the config before anything is allocated.

A config that passes the per-field rules can still need more memory than the machine has (``train.num_envs``
of ten million). :func:`resource_errors` adds up the big stores and refuses a config whose estimate exceeds
the device's memory, naming the fields of the largest store; :func:`check_buildable` also refuses an embedding
that does not fit the map. Both build parts on the ``meta`` device or at a small size, so they live beside the
builders rather than in the config's checks, which import nothing of the training loop.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from tensordict.utils import NestedKey

from mcrs.env.config import EnvConfig
from mcrs.env.torchrl_env import spec_leaves
from mcrs.experiment.schema import ConfigError
from mcrs.experiment.training.episodic import build_embedding
from mcrs.experiment.training.learner import build_agent, build_mixer
from mcrs.experiment.training.replay import STEP_KEYS

if TYPE_CHECKING:
    from mcrs.experiment.schema import Config

GiB = 1024**3
#: What a process holds before any store: Python, torch, TorchRL and the env code (the RSS at the start
#: of a run, rounded up: docs/PERFORMANCE.md, "Figures behind constants").
BASELINE_BYTES = 400 * 1024**2
FILLED_BYTES = 1  # a stored episode's ``filled`` flag per step (bool)
EPISODE_ID_BYTES = 8  # the episode's id per step (int64)


@dataclass
class Store:
    """One store of the estimate: its size and the fields, with their values, that set it."""

    name: str
    nbytes: int
    fields: str


def _nbytes(specs: Any) -> int:
    """Bytes of one sample of ``specs``, a leaf spec or nested dicts of them."""
    if isinstance(specs, dict):
        return sum(_nbytes(v) for v in specs.values())
    return specs.shape.numel() * specs.dtype.itemsize


def _step_specs(env: EnvConfig) -> dict[str, Any]:
    """The env's specs for one environment on the ``meta`` device, with nothing allocated."""
    return spec_leaves(env, 1, "meta")


def _leaf(specs: dict[str, Any], key: NestedKey) -> Any:
    for part in (key,) if isinstance(key, str) else key:
        specs = specs[part]
    return specs


def replay_step_bytes(env: EnvConfig) -> int:
    """Bytes of one step of a stored episode: the step keys, action, reward, done and terminated, the
    ``filled`` flag and the episode's id (int64, added for the memory's foreign-hit rate)."""
    specs = _step_specs(env)
    kept = [_leaf(specs["observation"], key) for key in STEP_KEYS]
    kept += [specs["action"], specs["reward"], specs["done"]["done"], specs["done"]["terminated"]]
    return sum(_nbytes(spec) for spec in kept) + FILLED_BYTES + EPISODE_ID_BYTES


def rollout_step_bytes(env: EnvConfig, hidden_dim: int) -> int:
    """Bytes of one step of a rollout: TorchRL keeps a root and a ``next`` copy of everything the env writes,
    one action, and the recurrent state (float32, ``[N, hidden_dim]``) in both copies."""
    specs = _step_specs(env)
    written = _nbytes(specs["observation"]) + _nbytes(specs["reward"]) + _nbytes(specs["done"])
    return 2 * written + _nbytes(specs["action"]) + 2 * env.n_uavs * 4 * hidden_dim


def memory_entry_bytes(env: EnvConfig, key_dim: int) -> int:
    """Bytes of one entry of the episodic memory D_E: counts (2 bytes a cell), positions, the key, return,
    step, flags, writing episode, EMU's counters and the index records."""
    positions = env.n_uavs + env.n_no_fly + env.n_targets
    return 2 * env.n_cells + 4 * positions + 4 * key_dim + 4 + 2 + 1 + 8 + 9 + 24


def network_bytes(cfg: Config, env: EnvConfig) -> tuple[int, str]:
    """Parameter bytes times five (weights, target, gradient, two optimiser moments), counted on the ``meta``
    device, and a problem if they cannot be built."""
    try:
        with torch.device("meta"):
            params = sum(p.numel() for p in build_agent(cfg.model, env).parameters())
            params += sum(p.numel() for p in build_mixer(cfg.algo, env).parameters())
    except (RuntimeError, ValueError, OverflowError, TypeError) as error:
        return 0, (str(error).strip().splitlines() or [type(error).__name__])[0]
    return 5 * 4 * params, ""


def estimate(cfg: Config, env: EnvConfig) -> list[Store]:
    """The stores of a run of ``cfg`` on a validated ``env``, largest first."""
    t, m, mem = cfg.train, cfg.model, cfg.algo.memory
    T = env.max_steps
    step, rollout = replay_step_bytes(env), rollout_step_bytes(env, m.hidden_dim)
    net, _ = network_bytes(cfg, env)
    stores = [
        Store("replay buffer", t.replay_episodes * (T + 1) * step,
              f"train.replay_episodes={t.replay_episodes} x env.max_steps={T}"),
        # the rollout, its episode layout and the replay's copy of it are alive together
        Store("collector batch", t.num_envs * T * (rollout + 2 * step),
              f"train.num_envs={t.num_envs} x env.max_steps={T}"),
        Store("evaluation batch", t.eval_episodes * T * rollout,
              f"train.eval_episodes={t.eval_episodes} x env.max_steps={T}"),
        Store("networks", net,
              f"model.hidden_dim={m.hidden_dim}, algo.mixing_embed_dim={cfg.algo.mixing_embed_dim}, "
              f"algo.hypernet_embed={cfg.algo.hypernet_embed}"),
        # one learner batch unrolled: inputs, GRU states and per-agent Q-values, kept for the backward pass
        Store("learner batch", t.batch_episodes * (T + 1) * (2 * step + env.n_uavs * 4 * 12 * m.hidden_dim),
              f"train.batch_episodes={t.batch_episodes} x env.max_steps={T}"),
    ]  # fmt: skip
    if mem.enabled:
        stores.append(
            Store("episodic memory", mem.capacity * memory_entry_bytes(env, mem.key_dim),
                  f"algo.memory.capacity={mem.capacity}")
        )  # fmt: skip
    return sorted(stores, key=lambda s: -s.nbytes)


def machine_memory(device: str) -> tuple[int, str]:
    """Bytes the run may use on ``device`` and what they are: the GPU's memory, or the host's, lowered by a
    cgroup limit."""
    parsed = torch.device(device)
    if parsed.type == "cuda" and torch.cuda.is_available():
        index = parsed.index if parsed.index is not None else torch.cuda.current_device()
        return torch.cuda.get_device_properties(index).total_memory, f"the memory of {device}"
    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = Path(path).read_text().strip()
        except OSError:
            continue
        if text.isdigit() and 0 < int(text) < total:
            return int(text), "this process's memory limit (cgroup)"
    return total, "this machine's memory"


def resource_errors(cfg: Config, env: EnvConfig) -> list[str]:
    """A memory estimate above what this machine has, as a problem line."""
    errors: list[str] = []
    _, problem = network_bytes(cfg, env)
    if problem:
        errors.append(
            f"model.hidden_dim={cfg.model.hidden_dim}, algo.mixing_embed_dim={cfg.algo.mixing_embed_dim}, "
            f"algo.hypernet_embed={cfg.algo.hypernet_embed}: the networks cannot be built ({problem})"
        )
        return errors
    stores = estimate(cfg, env)
    total = BASELINE_BYTES + sum(s.nbytes for s in stores)
    limit, what = machine_memory(str(cfg.device))
    if total > limit:
        top = stores[0]
        parts = ", ".join(f"{s.name} {s.nbytes / GiB:,.1f}" for s in stores[:3])
        errors.append(
            f"{top.fields}: the run would need about {total / GiB:,.1f} GiB ({parts} GiB), more than "
            f"{what} ({limit / GiB:,.1f} GiB): lower it"
        )
    return errors


def embedding_fit_errors(cfg: Config, env: EnvConfig) -> list[str]:
    """Build the embedding once, so one that does not fit the map is refused before any compute."""
    try:
        build_embedding(cfg, env)
    except ValueError as error:
        return [f"algo.memory.embedding={str(cfg.algo.memory.embedding)!r} does not fit {env.name}: {error}"]
    return []


def buildable_errors(cfg: Config, env: EnvConfig) -> list[str]:
    """Problems of a valid config that only building its parts shows: the embedding against the map, then the
    memory against the machine."""
    errors = embedding_fit_errors(cfg, env) if cfg.algo.memory.enabled else []
    return errors or resource_errors(cfg, env)


def check_buildable(cfg: Config, env: EnvConfig) -> None:
    """Raise :class:`ConfigError`, as :func:`~mcrs.experiment.config.validate` does, when the run's parts do
    not fit the map or the machine."""
    errors = buildable_errors(cfg, env)
    if errors:
        raise ConfigError("invalid config:\n  - " + "\n  - ".join(errors))
