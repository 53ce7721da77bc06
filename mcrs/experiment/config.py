"""The training config: its typed schemas (:mod:`mcrs.experiment.schema`, registered in Hydra's ConfigStore)
and their validation.

One typed node per concept: ``env`` (the scenario: the map, team, sensing, communication and reward of the
paper's tables 2-3), ``algo`` (with ``algo.memory``), ``model``, ``train``, ``logger``; the env's runtime
fields come from ``train.num_envs`` and ``device``. Choices are enums. The schemas make Hydra refuse
unknown keys, wrong types and unknown choices while composing (``algo.lrr=1``, ``train.lr=abc``,
``algo.mixer=qtran`` fail before anything runs); :func:`validate` then checks values once, with one message
per problem naming the field, the value and what is allowed. Each node's rules are beside its dataclass
(``AlgoConfig.errors()``, ..., in :mod:`mcrs.experiment.schema`), the scenario's are
:class:`mcrs.env.EnvConfig`'s own, and the rules that span nodes or need the machine are here.

The schemas are in :mod:`mcrs.experiment.schema` and re-exported here, where users import them. These
checks read values only and import nothing of the training loop; whether the run's parts fit the map and
the machine is checked where the :class:`~mcrs.experiment.training.trainer.Experiment` builds them
(:func:`~mcrs.experiment.training.resources.check_buildable`).

    config = compose("algo=qmix", "env=map20", "seed=3")     # a typed Config, as mcrs-train composes it
    Experiment(config, "outputs/my_run").run()
"""

from __future__ import annotations

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
    MAX_LR,
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
    "MAX_LR",
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


#: Fields whose own check takes any value and names what is allowed (``threads``: "auto" or a count; the
#: scenario: :class:`mcrs.env.EnvConfig`'s rules).
_OWN_TYPE_CHECK = frozenset({"threads", "env"})


def _fits(value: Any, kind: Any) -> bool:
    """Whether ``value`` has the type ``kind`` of a schema field (bool is neither int nor float; an int
    is a float; a choice is checked by its node's ``errors()``)."""
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
    """Every problem of a config, and the env config it runs on (None when the env part is wrong): the
    scenario's rules, each node's own (``errors()`` beside its dataclass in :mod:`mcrs.experiment.schema`),
    then the rules of the whole config (:func:`_config_errors`)."""
    errors: list[str] = _type_errors(cfg)
    if errors:  # the value checks below compare values: they need the types right
        return errors, None
    t = cfg.train
    env_config = None
    problem = device_problem(cfg.device)  # no torch import for "cpu"; a GPU asked for is checked at once
    try:  # the scenario's own rules (on the CPU when the device is wrong, one env when train.num_envs is:
        # both are reported by their own rules)
        env_config = EnvConfig.from_scenario(
            cfg.env,
            num_envs=t.num_envs if isinstance(t.num_envs, int) and t.num_envs >= 1 else 1,
            device="cpu" if problem or not deep else cfg.device,
        )
    except (ValueError, TypeError) as error:
        errors += _env_errors(str(error))
    for node in (cfg.algo, cfg.model, cfg.logger, cfg.train):
        errors += node.errors()
    errors += _config_errors(cfg, problem)
    return errors, env_config


def _config_errors(cfg: Config, device: str | None) -> list[str]:
    """The rules of the whole config, which span nodes or need the machine: the seed, the device
    (``device``: its problem, found before the scenario was built on it), the episodic memory against the
    scenario, the labels that name run directories, and the threads (read from
    :mod:`mcrs.experiment.util.threads`, imported only when a config is checked)."""
    errors: list[str] = []
    if not 0 <= cfg.seed <= MAX_SEED:
        errors.append(f"seed={cfg.seed}: must be in [0, 2**63 - 1]")
    if device:
        errors.append(f"device={cfg.device!r}: {device}")
    memory = cfg.algo.memory
    max_steps = cfg.env.max_steps
    if memory.enabled and isinstance(max_steps, int) and max_steps >= MAX_STEPS_LIMIT:
        errors.append(
            f"env.max_steps={max_steps}: the episodic memory stores steps as int16: at most {MAX_STEPS_LIMIT - 1}"
        )
    decay = getattr(cfg.env, "evidence_decay", 0.0)
    if memory.enabled and isinstance(decay, (int, float)) and decay > 0:
        errors.append(
            f"env.evidence_decay={decay}: the episodic memory stores integer detection counts, and decayed "
            "counts are fractions: set env.evidence_decay=0 or algo.memory.enabled=false"
        )
    labels = {
        "algo.name": cfg.algo.name,
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
    from mcrs.experiment.util.threads import cpu_count, threads_problem

    problem = threads_problem(cfg.threads, cpu_count())
    if problem:
        errors.append(f"threads={cfg.threads}: {problem}")
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
