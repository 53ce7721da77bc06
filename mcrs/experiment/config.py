"""The training config: its typed schemas (:mod:`mcrs.experiment.schema`, registered in Hydra's ConfigStore)
and their validation.

One typed node per concept: ``env`` (the scenario: the map, team, sensing, communication and reward of the
paper's tables 2-3), ``algo`` (with ``algo.memory``), ``model``, ``train``, ``logger``; the env's runtime
fields come from ``train.num_envs`` and ``device``. Choices are enums. The schemas make Hydra refuse
unknown keys, wrong types and unknown choices while composing (``algo.lrr=1``, ``train.lr=abc``,
``algo.mixer=qtran`` fail before anything runs); :func:`validate` then checks values once, with one message
per problem naming the field, the value and what is allowed. The scenario's rules are
:class:`mcrs.env.EnvConfig`'s own.

The schemas are in :mod:`mcrs.experiment.schema` and re-exported here, where users import them. These
checks read values only and import nothing of the training loop; whether the run's parts fit the map and
the machine is checked where the :class:`~mcrs.experiment.training.trainer.Experiment` builds them
(:func:`~mcrs.experiment.training.resources.check_buildable`).

    config = compose("algo=qmix", "env=map20", "seed=3")     # a typed Config, as mcrs-train composes it
    Experiment(config, "outputs/my_run").run()
"""

from __future__ import annotations

import math
import types
import typing
from dataclasses import fields, is_dataclass
from enum import Enum
from typing import Any

from omegaconf import DictConfig
from omegaconf.errors import OmegaConfBaseException

from mcrs.env.config import EnvConfig, device_problem
from mcrs.experiment.schema import (
    CONFIG_DIR,
    DELTA_RULES,
    EMBEDDINGS,
    INCENTIVES,
    MAX_MEMORY_CAPACITY,
    MAX_SEED,
    MAX_STEPS_LIMIT,
    MIXERS,
    RESUME_MUTABLE,
    SHAPES,
    TIME_LIMITS,
    AlgoConfig,
    Choice,
    Collector,
    Config,
    ConfigError,
    DeltaRule,
    Embedding,
    Incentive,
    LoggerBackend,
    LoggerConfig,
    MemoryConfig,
    Mixer,
    ModelConfig,
    ModelName,
    Neighbourhood,
    Optimizer,
    TimeLimit,
    TrainConfig,
    WandbMode,
    as_dictconfig,
    as_typed,
    register_configs,
    to_container,
)
from mcrs.experiment.util.untrusted import PLAIN_NAME

__all__ = [
    "CONFIG_DIR",
    "DELTA_RULES",
    "EMBEDDINGS",
    "INCENTIVES",
    "MAX_MEMORY_CAPACITY",
    "MAX_SEED",
    "MAX_STEPS_LIMIT",
    "MIXERS",
    "RESUME_MUTABLE",
    "SHAPES",
    "TIME_LIMITS",
    "AlgoConfig",
    "Choice",
    "Collector",
    "Config",
    "ConfigError",
    "DeltaRule",
    "Embedding",
    "Incentive",
    "LoggerBackend",
    "LoggerConfig",
    "MemoryConfig",
    "Mixer",
    "ModelConfig",
    "ModelName",
    "Neighbourhood",
    "Optimizer",
    "TimeLimit",
    "TrainConfig",
    "WandbMode",
    "as_dictconfig",
    "as_typed",
    "compose",
    "register_configs",
    "to_container",
    "validate",
    "validation_errors",
]


#: Learning rates above this are refused: no optimiser here takes a step larger than the parameters.
MAX_LR = 1.0


def _positive(errors: list[str], name: str, value: float, allow_zero: bool = False) -> None:
    ok = value >= 0 if allow_zero else value > 0
    if not ok or (isinstance(value, float) and not math.isfinite(value)):
        errors.append(f"{name}={value}: must be {'>= 0' if allow_zero else '> 0'}")


#: Fields whose own check takes any value and names what is allowed (``threads``: "auto" or a count; the
#: scenario: :class:`mcrs.env.EnvConfig`'s rules).
_OWN_TYPE_CHECK = frozenset({"threads", "env"})


def _fits(value: Any, kind: Any) -> bool:
    """Whether ``value`` has the type ``kind`` of a schema field (bool is neither int nor float; an int
    is a float; a choice is checked by :func:`_choice`)."""
    if kind is type(None):
        return value is None
    if kind is bool:
        return isinstance(value, bool)
    if kind is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if kind is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if kind is str:
        return isinstance(value, str)
    if isinstance(kind, type) and issubclass(kind, Enum):
        return isinstance(value, (str, Enum))
    if typing.get_origin(kind) is list:
        return isinstance(value, (list, tuple))
    return True


def _type_errors(node: Any, prefix: str = "") -> list[str]:
    """Fields of a :class:`Config` built in Python whose value has the wrong type, each named in full
    (``train.lr='abc': must be of type float (got str)``). OmegaConf checks a composed config's types; a dataclass built in
    Python reaches :func:`validate` unchecked, and the value checks would fail on a comparison."""
    errors = []
    hints = typing.get_type_hints(type(node))
    for f in fields(node):
        name, value = prefix + f.name, getattr(node, f.name)
        if name in _OWN_TYPE_CHECK:
            continue
        if is_dataclass(value):
            errors += _type_errors(value, f"{name}.")
            continue
        hint = hints[f.name]
        union = typing.get_origin(hint) in (typing.Union, types.UnionType)
        kinds = typing.get_args(hint) if union else (hint,)
        if not any(_fits(value, kind) for kind in kinds):
            wanted = " or ".join("None" if k is type(None) else getattr(k, "__name__", str(k)) for k in kinds)
            errors.append(f"{name}={value!r}: must be of type {wanted} (got {type(value).__name__})")
    return errors


def _choice(errors: list[str], name: str, value: Any, allowed: type[Choice]) -> None:
    """A choice of a :class:`Config` built in Python, which OmegaConf never sees (``as_typed`` returns it
    as it is): a composed config's choices were refused by OmegaConf's structured schema already, so this
    fires only for the dataclass. OmegaConf's own check of such an instance (``OmegaConf.structured``)
    stops at the first bad field and names it without its node (``mixer``, not ``algo.mixer``), so every
    bad choice is named here, in full."""
    values = [member.value for member in allowed]
    if str(value) not in values:
        errors.append(f"{name}={str(value)!r}: allowed values are {', '.join(values)}")


def validation_errors(cfg: Config | DictConfig, deep: bool = True) -> list[str]:
    """Every problem of a config's values, one message each (empty when they are right).

    ``deep=False`` builds the scenario on the CPU, so that a command line can check its config before it
    loads the training stack (a device other than the CPU is checked either way). Whether the run's parts
    fit (the memory it needs, the embedding on the map) is checked where they are built:
    :func:`mcrs.experiment.training.resources.check_buildable`, which :class:`Experiment` calls."""
    return _problems(as_typed(cfg), deep)[0]


def _env_errors(message: str) -> list[str]:
    """The scenario's problems as the config's lines (``env.width=0: must be ...``), one per problem."""
    head = "invalid environment config:\n  - "
    if not message.startswith(head):
        return [f"env: {message}"]
    return [f"env.{line}" for line in message.removeprefix(head).split("\n  - ")]


def _problems(cfg: Config, deep: bool = True) -> tuple[list[str], EnvConfig | None]:
    """Every problem of a config, and the env config it runs on (None when the env part is wrong)."""
    errors: list[str] = _type_errors(cfg)
    if errors:  # the value checks below compare values: they need the types right
        return errors, None
    t = cfg.train
    env_config = None
    problem = device_problem(cfg.device)  # no torch import for "cpu"; a GPU asked for is checked at once
    if problem:
        errors.append(f"device={cfg.device!r}: {problem}")
    try:  # the scenario's own rules (on the CPU when the device is wrong, one env when train.num_envs is:
        # both are reported by their own rules)
        env_config = EnvConfig.from_scenario(
            cfg.env,
            num_envs=t.num_envs if isinstance(t.num_envs, int) and t.num_envs >= 1 else 1,
            device="cpu" if problem or not deep else cfg.device,
        )
    except (ValueError, TypeError) as error:
        errors += _env_errors(str(error))
    errors += _algo_errors(cfg)
    errors += _train_errors(cfg)
    errors += _run_errors(cfg)
    return errors, env_config


def _algo_errors(cfg: Config) -> list[str]:
    """The choices, then the algorithm's and its memory's fields."""
    errors: list[str] = []
    a, lg, t = cfg.algo, cfg.logger, cfg.train
    _choice(errors, "algo.mixer", a.mixer, Mixer)
    _choice(errors, "algo.time_limit", a.time_limit, TimeLimit)
    _choice(errors, "train.optimizer", t.optimizer, Optimizer)
    _choice(errors, "logger.backend", lg.backend, LoggerBackend)
    _choice(errors, "logger.wandb_mode", lg.wandb_mode, WandbMode)
    if a.hypernet_layers not in (1, 2):
        errors.append(f"algo.hypernet_layers={a.hypernet_layers}: allowed values are 1, 2")
    if a.qplex_adv_layers not in (1, 2, 3):
        errors.append(f"algo.qplex_adv_layers={a.qplex_adv_layers}: allowed values are 1, 2, 3")
    for name in ("mixing_embed_dim", "hypernet_embed", "qplex_kernels", "reward_scale"):
        _positive(errors, f"algo.{name}", getattr(a, name))
    for name in ("gamma", "td_lambda"):
        if not 0.0 <= getattr(a, name) <= 1.0:
            errors.append(f"algo.{name}={getattr(a, name)}: must be in [0, 1]")
    errors += _memory_errors(cfg)
    return errors


def _train_errors(cfg: Config) -> list[str]:
    """The model's size, the logging interval and the training schedule."""
    errors: list[str] = []
    m, lg, t = cfg.model, cfg.logger, cfg.train
    _positive(errors, "model.hidden_dim", m.hidden_dim)
    _positive(errors, "logger.log_interval", lg.log_interval)
    for name in (
        "total_env_steps", "num_envs", "batch_episodes", "replay_episodes", "lr", "optim_eps",
        "grad_clip", "eps_anneal_steps", "target_update_episodes", "eval_interval", "eval_episodes",
        "checkpoint_interval",
    ):  # fmt: skip
        _positive(errors, f"train.{name}", getattr(t, name))
    for name, lr in (("train.lr", t.lr), ("algo.memory.embedding_lr", cfg.algo.memory.embedding_lr)):
        if math.isfinite(lr) and lr > MAX_LR:  # RMSprop's squared gradients overflow at 1e300
            errors.append(f"{name}={lr}: must be <= {MAX_LR:g} (a larger step diverges at once)")
    _positive(errors, "train.updates_per_episode", t.updates_per_episode, allow_zero=True)
    _positive(errors, "train.checkpoint_minutes", t.checkpoint_minutes, allow_zero=True)
    if t.keep_checkpoints < 0:
        errors.append(
            f"train.keep_checkpoints={t.keep_checkpoints}: must be >= 0 (0 keeps every weight file)"
        )
    for name in ("eps_start", "eps_end", "rmsprop_alpha"):
        if not 0.0 <= getattr(t, name) <= 1.0:
            errors.append(f"train.{name}={getattr(t, name)}: must be in [0, 1]")
    if t.eps_end > t.eps_start:
        errors.append(f"train.eps_end={t.eps_end} > train.eps_start={t.eps_start}: epsilon only decays")
    if t.replay_episodes < t.batch_episodes:
        errors.append(
            f"train.replay_episodes={t.replay_episodes} < train.batch_episodes={t.batch_episodes}: "
            "the buffer must hold a whole batch"
        )
    _choice(errors, "train.collector", t.collector, Collector)
    if t.collector_workers < 1:
        errors.append(f"train.collector_workers={t.collector_workers}: must be >= 1")
    elif str(t.collector) == "multiprocess" and t.num_envs % t.collector_workers:
        errors.append(
            f"train.num_envs={t.num_envs} is not divisible by train.collector_workers={t.collector_workers}: "
            "each worker collects the same number of whole episodes"
        )
    if not 0 <= t.eval_seed <= MAX_SEED:
        errors.append(f"train.eval_seed={t.eval_seed}: must be in [0, 2**63 - 1]")
    if not 0 <= cfg.seed <= MAX_SEED:
        errors.append(f"seed={cfg.seed}: must be in [0, 2**63 - 1]")
    return errors


def _run_errors(cfg: Config) -> list[str]:
    """The run's names and labels (they name directories), the incentive threshold and the threads."""
    errors: list[str] = []
    a, m, lg = cfg.algo, cfg.model, cfg.logger
    _choice(errors, "model.name", m.name, ModelName)
    if not str(lg.project).strip():
        errors.append(f"logger.project={lg.project!r}: must be a non-empty name")
    labels = {
        "algo.name": a.name,
        "env.name": cfg.env.name,
        "experiment": cfg.experiment,
        "budget": cfg.budget,
    }
    for field_name, label in labels.items():
        if not PLAIN_NAME.fullmatch(str(label)):  # '..' or '.' would put the run outside outputs/
            errors.append(
                f"{field_name}={str(label)!r}: must be a non-empty label without '/', a plain name (letters, "
                "digits, _ . + = -, not starting with '.'): it names run directories"
            )
    if not math.isfinite(a.incentive_threshold):
        errors.append(f"algo.incentive_threshold={a.incentive_threshold}: must be a finite return")
    from mcrs.experiment.util.threads import cpu_count, threads_problem

    problem = threads_problem(cfg.threads, cpu_count())
    if problem:
        errors.append(f"threads={cfg.threads}: {problem}")
    return errors


def _memory_errors(cfg: Config) -> list[str]:
    """Problems of the episodic-memory fields (only checked where they matter)."""
    errors: list[str] = []
    a, mem = cfg.algo, cfg.algo.memory
    _choice(errors, "algo.incentive", a.incentive, Incentive)
    _choice(errors, "algo.memory.embedding", mem.embedding, Embedding)
    _choice(errors, "algo.memory.delta_rule", mem.delta_rule, DeltaRule)
    _choice(errors, "algo.memory.neighbourhood", mem.neighbourhood, Neighbourhood)
    if a.memory_weight < 0 or not math.isfinite(a.memory_weight):
        errors.append(f"algo.memory_weight={a.memory_weight}: must be >= 0 (lambda of eq. 32)")
    _positive(errors, "algo.curiosity_scale", a.curiosity_scale, allow_zero=True)
    _positive(errors, "algo.curiosity_decay_cycle", a.curiosity_decay_cycle)
    for name in ("curiosity_decay_rate", "curiosity_tau"):
        if not 0.0 <= getattr(a, name) <= 1.0:
            errors.append(f"algo.{name}={getattr(a, name)}: must be in [0, 1]")
    uses_memory = a.memory_weight > 0 or str(a.incentive) != "none"
    if uses_memory and not mem.enabled:
        errors.append(
            f"algo.memory.enabled=false, but algo.memory_weight={a.memory_weight} and "
            f"algo.incentive={a.incentive!r} need the episodic memory: set algo.memory.enabled=true"
        )
    if mem.delta <= 0 or not math.isfinite(mem.delta):
        errors.append(f"algo.memory.delta={mem.delta}: must be > 0")
    if mem.capacity < 1:
        errors.append(f"algo.memory.capacity={mem.capacity}: must be >= 1 entry")
    elif mem.capacity > MAX_MEMORY_CAPACITY:
        errors.append(f"algo.memory.capacity={mem.capacity}: must be <= 2**31 - 1 entries (int32 slots)")
    for name in ("key_dim", "hidden_dim", "embedding_interval", "embedding_samples", "embedding_batch"):
        _positive(errors, f"algo.memory.{name}", getattr(mem, name))
    _positive(errors, "algo.memory.embedding_lr", mem.embedding_lr)
    _positive(errors, "algo.memory.state_weight", mem.state_weight, allow_zero=True)
    if not mem.embedding_grad_clip > 0:
        errors.append(
            f"algo.memory.embedding_grad_clip={mem.embedding_grad_clip}: must be > 0 (inf: no clipping)"
        )
    if len(mem.cnn_channels) != 3 or any(c < 1 for c in mem.cnn_channels):
        errors.append(f"algo.memory.cnn_channels={list(mem.cnn_channels)}: must be 3 positive channel counts")
    if mem.embedding_batch > mem.embedding_samples > 0:
        errors.append(
            f"algo.memory.embedding_batch={mem.embedding_batch} > algo.memory.embedding_samples="
            f"{mem.embedding_samples}: each training of the embedding draws its batches from the samples"
        )
    max_steps = cfg.env.max_steps
    if mem.enabled and isinstance(max_steps, int) and max_steps >= MAX_STEPS_LIMIT:
        errors.append(
            f"env.max_steps={max_steps}: the episodic memory stores steps as int16: at most {MAX_STEPS_LIMIT - 1}"
        )
    decay = getattr(cfg.env, "evidence_decay", 0.0)
    if mem.enabled and isinstance(decay, (int, float)) and decay > 0:
        errors.append(
            f"env.evidence_decay={decay}: the episodic memory stores integer detection counts, and decayed "
            "counts are fractions: set env.evidence_decay=0 or algo.memory.enabled=false"
        )
    if mem.enabled and mem.key_dim > 8:
        errors.append(
            f"algo.memory.key_dim={mem.key_dim}: at most 8 (each look-up checks 2^key_dim grid cells)"
        )
    return errors


def validate(cfg: Config | DictConfig) -> EnvConfig:
    """Raise :class:`ConfigError` listing every problem of ``cfg``'s values; return the env config it runs
    on. :class:`~mcrs.experiment.training.trainer.Experiment` then checks that its parts fit
    (:func:`~mcrs.experiment.training.resources.check_buildable`)."""
    errors, env_config = _problems(as_typed(cfg))
    if errors:
        raise ConfigError("invalid config:\n  - " + "\n  - ".join(errors))
    assert env_config is not None
    return env_config


def compose(*overrides: str) -> Config:
    """The typed config ``mcrs-train <overrides>`` would run, composed from the packaged presets
    (``compose("algo=qmix", "env=map20", "train.total_env_steps=100000")``).

    A bad override raises :class:`ConfigError` with the line ``mcrs-train`` prints for it
    (``env.comm_rage: unknown key; the keys of env (closest first): comm_range, ...``)."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.errors import HydraException

    from mcrs.experiment.util.messages import describe

    wrong = [o for o in overrides if not isinstance(o, str)]
    if wrong:  # compose(["algo=qmix"]) would fail deep in Hydra's parser
        raise TypeError(
            f"compose takes each override as a string argument, compose('algo=qmix', 'env=map20'); got a "
            f"{type(wrong[0]).__name__} (a list of overrides: compose(*overrides))"
        )
    register_configs()
    try:
        with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
            cfg = hydra_compose(config_name="config", overrides=list(overrides))
    except (HydraException, OmegaConfBaseException) as error:
        raise ConfigError(describe(error)) from None
    return as_typed(cfg)
