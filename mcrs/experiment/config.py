"""Typed schemas of the training config, registered in Hydra's ConfigStore, and their validation.

One typed node per concept: ``env`` (the scenario: the map, team, sensing, communication and reward of the
paper's tables 2-3), ``algo`` (with ``algo.memory``), ``model``, ``train``, ``logger``; the env's runtime
fields come from ``train.num_envs`` and ``device``. Choices are enums. The schemas make Hydra refuse
unknown keys, wrong types and unknown choices while composing (``algo.lrr=1``, ``train.lr=abc``,
``algo.mixer=qtran`` fail before anything runs); :func:`validate` then checks values once, with one message
per problem naming the field, the value and what is allowed. The scenario's rules are
:class:`mcrs.env.EnvConfig`'s own.

    config = compose("algo=qmix", "env=map20", "seed=3")     # a typed Config, as mcrs-train composes it
    Experiment(config, "outputs/my_run").run()
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from mcrs.env.config import EnvConfig, ScenarioConfig, device_problem
from mcrs.experiment.untrusted import PLAIN_NAME

# The choices, as the modules that implement them define them (mcrs.models.mixers.MIXERS, ...; a test keeps
# them equal): written out here so that composing and checking a config imports neither torch nor TorchRL,
# and a mistyped override is refused in a second, not after the whole stack has loaded.
MIXERS = ("qmix", "vdn", "qplex")
EMBEDDINGS = ("random", "fc", "cnn")
DELTA_RULES = ("volume", "literal")
SHAPES = ("ball", "box")
TIME_LIMITS = ("terminal", "bootstrap")
INCENTIVES = ("none", "fixed", "change")


class Choice(str, Enum):
    """A config choice: Hydra checks it against the members while composing; it compares equal to, prints
    and formats as its value (``Mixer.qmix == "qmix"``), as ``enum.StrEnum`` does from Python 3.11 on."""

    def __str__(self) -> str:
        return str(self.value)

    def __format__(self, spec: str) -> str:
        return format(str(self.value), spec)


def _choices(name: str, values: tuple[str, ...]) -> type[Choice]:
    return Choice(name, [(value, value) for value in values])  # member name = value: what users type


Mixer = _choices("Mixer", MIXERS)
Optimizer = _choices("Optimizer", ("rmsprop", "adam"))
LoggerBackend = _choices("LoggerBackend", ("csv", "wandb", "tensorboard"))
WandbMode = _choices("WandbMode", ("offline", "online"))
ModelName = _choices("ModelName", ("gru",))
Collector = _choices("Collector", ("single", "multiprocess"))
Embedding = _choices("Embedding", EMBEDDINGS)  # random (EMC) | fc (SEMU) | cnn (CNN-SEMU)
Incentive = _choices("Incentive", INCENTIVES)
DeltaRule = _choices("DeltaRule", DELTA_RULES)
Neighbourhood = _choices("Neighbourhood", SHAPES)
TimeLimit = _choices("TimeLimit", TIME_LIMITS)
MAX_SEED = 2**63 - 1  # batch seeds are taken modulo 2**63; torch's generator takes 64-bit seeds
MAX_MEMORY_CAPACITY = 2**31 - 1  # slots of the episodic memory are int32
MAX_STEPS_LIMIT = 2**15  # the episodic memory stores an entry's step as int16 (mcrs.memory.episodic)
CONFIG_DIR = str(Path(__file__).resolve().parents[1] / "conf")  # the packaged Hydra presets
#: Fields a resumed run may change (how long, how it reports); everything else must match the run.
RESUME_MUTABLE = (
    "train.total_env_steps",
    "logger",
    "resume",
    "overwrite",
    "threads",
    "report",
    "train.eval_interval",
    "train.checkpoint_interval",
    "train.checkpoint_minutes",
    "train.keep_checkpoints",
    "train.collector",  # how episodes are collected (a crashed multiprocess run may go on in one process;
    "train.collector_workers",  # the episodes then differ from an uninterrupted run's)
)


class ConfigError(ValueError):
    """A config that cannot run; the message lists every problem."""


@dataclass
class MemoryConfig:
    """The episodic buffer D_E and its state embedding phi (paper Algorithm 1, eq. 31; table 3)."""

    enabled: bool = False
    embedding: Embedding = Embedding.cnn  # random (EMC) | fc (SEMU, EMU's dCAE) | cnn (CNN-SEMU)
    key_dim: int = 4  # dimension of the keys x = phi(s)
    hidden_dim: int = 64  # width of the encoder and decoder layers
    cnn_channels: list[int] = field(default_factory=lambda: [8, 16, 32])  # the CNN's three conv layers
    capacity: int = 1_000_000  # entries; the oldest are evicted when full
    delta: float = 1.3e-3  # table 3 / eq. 35; what it means is delta_rule's (mcrs/memory/delta.py)
    delta_rule: DeltaRule = (
        DeltaRule.volume
    )  # volume: eq. 35's key-space volume per entry | literal: the tolerance
    neighbourhood: Neighbourhood = (
        Neighbourhood.box
    )  # box: EMU's |z_i - z'_i| <= tol in every dimension | ball: Euclidean < tol
    embedding_interval: int = 10_000  # t_emb: env steps between trainings of the embedding
    embedding_samples: int = 102_400  # memory entries drawn per training of the embedding
    embedding_batch: int = 1024
    embedding_lr: float = 5e-4
    state_weight: float = 0.1  # lambda_1 of eq. 31: weight of the state reconstruction
    embedding_grad_clip: float = 10.0  # gradient-norm clip of the embedding's training (EMU: pymarl's 10)
    counter_reset: bool = False  # EMU's flag_memory_cnt_reset: a desirability shift restarts N_call, N_xi


@dataclass
class AlgoConfig:
    """The value-factorisation algorithm: which mixer, the TD target and the episodic-memory terms."""

    name: str = "qmix"  # label of the algorithm (run names, reports)
    mixer: Mixer = Mixer.qmix
    mixing_embed_dim: int = 32  # QMIX mixing width
    hypernet_embed: int = 64  # hidden width of the hypernetworks (QMIX, QPLEX)
    hypernet_layers: int = 2  # QMIX hypernetwork depth: 1 (TorchRL) or 2 (pymarl)
    qplex_kernels: int = 4  # QPLEX attention heads of the advantage weights
    qplex_adv_layers: int = 1  # depth of QPLEX's advantage-weight extractors: 1 (SMAC setting) to 3
    gamma: float = 0.99
    td_lambda: float = 0.0  # 0: one-step targets (pymarl); 0.6 in pymarl2
    double_q: bool = True
    # the horizon T in the TD target: terminal (no bootstrap at T, as the memory's returns) | bootstrap
    time_limit: TimeLimit = TimeLimit.terminal
    memory: MemoryConfig = field(default_factory=MemoryConfig)
    memory_weight: float = 0.0  # lambda of eq. 32: weight of the one-step memory target (0: off)
    incentive: Incentive = (
        Incentive.none
    )  # EMU's episodic incentive: none | fixed (return threshold) | change
    incentive_threshold: float = 365.0  # "fixed": episodes with a return >= this are desirable
    curiosity_scale: float = 0.0  # EMC's curiosity reward scale (0: off)
    curiosity_decay_rate: float = 0.9  # the scale is multiplied by this ...
    curiosity_decay_cycle: int = 100_000  # ... every this many env steps
    curiosity_tau: float = 0.005  # soft target update of the curiosity's VDN learner


@dataclass
class ModelConfig:
    """The shared recurrent agent network."""

    name: ModelName = ModelName.gru
    hidden_dim: int = 64
    agent_id: bool = True  # one-hot agent id as input
    last_action: bool = True  # one-hot last action as input


@dataclass
class LoggerConfig:
    """Where metrics go (TorchRL loggers). Nothing leaves the machine unless wandb_mode=online."""

    backend: LoggerBackend = LoggerBackend.csv
    project: str = "mcrs"  # wandb project
    wandb_mode: WandbMode = WandbMode.offline
    log_interval: int = 2000  # env steps between train/ and time/ log rows (means over the interval)
    progress_bar: bool = True
    video: bool = False  # one greedy evaluation episode as a video at every evaluation (GIF; tb, wandb)


@dataclass
class TrainConfig:
    """The training loop. Intervals count env steps (agent-team transitions), as in pymarl."""

    total_env_steps: int = 2_000_000
    num_envs: int = 1  # episodes collected in parallel per collector batch
    batch_episodes: int = 32  # episodes per learner update
    replay_episodes: int = 5000  # replay capacity in episodes
    updates_per_episode: float = 1.0  # learner updates per collected episode
    optimizer: Optimizer = Optimizer.rmsprop
    lr: float = 5e-4
    rmsprop_alpha: float = 0.99
    optim_eps: float = 1e-5
    grad_clip: float = 10.0
    eps_start: float = 1.0
    eps_end: float = 0.05
    eps_anneal_steps: int = 50_000
    target_update_episodes: int = 200  # hard target update period, in collected episodes
    eval_interval: int = 10_000
    eval_episodes: int = 32
    eval_seed: int = 1_000_000  # the evaluation episodes are the same at every evaluation
    checkpoint_interval: int = 100_000
    checkpoint_minutes: float = 10.0  # also checkpoint every this many minutes of wall clock (0: off)
    keep_checkpoints: int = (
        5  # weight files model_<steps>.pt kept, the newest (0: all); last.pt is always kept
    )
    save_replay: bool = True  # checkpoints carry the replay buffer, so a resumed run is identical
    collector: Collector = (
        Collector.single
    )  # single (one process) | multiprocess (TorchRL MultiSyncCollector)
    collector_workers: int = 2  # multiprocess: worker processes, each collecting num_envs / workers episodes


@dataclass
class Config:
    """The whole ``mcrs-train`` config (``conf/config.yaml``)."""

    env: ScenarioConfig = field(default_factory=ScenarioConfig)  # the scenario; conf/env/ holds the presets
    algo: AlgoConfig = field(default_factory=AlgoConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    preset: str = "pymarl"  # label of the hyper-parameter preset (conf/preset/)
    experiment: str = "none"  # label of the section-6 preset that launched the run (conf/experiment/)
    budget: str = "none"  # label of the budget (conf/budget/): smoke, cpu or paper
    seed: int = 0
    device: str = "cpu"  # env, acting and learner device: cpu, cuda, cuda:0 ... (the env's runtime field)
    threads: str = "auto"  # torch CPU threads: auto (the cores the load leaves free), 0 (torch's: all) or N
    report: bool = False  # after training: evaluate with the heuristics, write report/ (table, curve, GIF)
    resume: str | None = None  # a run directory to continue
    overwrite: bool = False  # a fresh run may replace the previous run in a non-empty hydra.run.dir


def register_configs() -> None:
    """Register the schemas (``config.yaml`` names ``mcrs_config`` in its defaults)."""
    cs = ConfigStore.instance()
    cs.store(name="mcrs_config", node=Config)


def _positive(errors: list[str], name: str, value: float, allow_zero: bool = False) -> None:
    ok = value >= 0 if allow_zero else value > 0
    if not ok or (isinstance(value, float) and not math.isfinite(value)):
        errors.append(f"{name}={value}: must be {'>= 0' if allow_zero else '> 0'}")


def _choice(errors: list[str], name: str, value: Any, allowed: type[Choice]) -> None:
    """Hydra checks enums while composing; a Python caller may hand over any string."""
    values = [member.value for member in allowed]
    if str(value) not in values:
        errors.append(f"{name}={str(value)!r}: allowed values are {', '.join(values)}")


def validation_errors(cfg: Config | DictConfig, deep: bool = True) -> list[str]:
    """Every problem of a config, one message each (empty when it can run).

    ``deep=False`` leaves out what needs torch (the device, the memory and CPU the run needs, whether the
    embedding fits the map): the checks a command line makes before it loads the training stack."""
    return _problems(as_typed(cfg), deep)[0]


def _problems(cfg: Config, deep: bool = True) -> tuple[list[str], EnvConfig | None]:
    """Every problem of a config, and the env config it runs on (None when the env part is wrong)."""
    errors: list[str] = []
    a, m, lg, t = cfg.algo, cfg.model, cfg.logger, cfg.train
    env_config = None
    problem = device_problem(cfg.device) if deep else None
    if problem:
        errors.append(f"device={cfg.device!r}: {problem}")
    try:  # the scenario's own rules (on the CPU when the device is wrong: that is reported above)
        env_config = EnvConfig.from_scenario(
            cfg.env, num_envs=t.num_envs, device="cpu" if problem or not deep else cfg.device
        )
    except (ValueError, TypeError) as error:
        errors.append(f"env: {error}")
    _choice(errors, "algo.mixer", a.mixer, Mixer)
    _choice(errors, "algo.time_limit", a.time_limit, TimeLimit)
    _choice(errors, "train.optimizer", t.optimizer, Optimizer)
    _choice(errors, "logger.backend", lg.backend, LoggerBackend)
    _choice(errors, "logger.wandb_mode", lg.wandb_mode, WandbMode)
    if a.hypernet_layers not in (1, 2):
        errors.append(f"algo.hypernet_layers={a.hypernet_layers}: allowed values are 1, 2")
    if a.qplex_adv_layers not in (1, 2, 3):
        errors.append(f"algo.qplex_adv_layers={a.qplex_adv_layers}: allowed values are 1, 2, 3")
    for name in ("mixing_embed_dim", "hypernet_embed", "qplex_kernels"):
        _positive(errors, f"algo.{name}", getattr(a, name))
    for name in ("gamma", "td_lambda"):
        if not 0.0 <= getattr(a, name) <= 1.0:
            errors.append(f"algo.{name}={getattr(a, name)}: must be in [0, 1]")
    errors += _memory_errors(cfg, env_config if deep else None)
    _positive(errors, "model.hidden_dim", m.hidden_dim)
    _positive(errors, "logger.log_interval", lg.log_interval)
    for name in (
        "total_env_steps", "num_envs", "batch_episodes", "replay_episodes", "lr", "optim_eps",
        "grad_clip", "eps_anneal_steps", "target_update_episodes", "eval_interval", "eval_episodes",
        "checkpoint_interval",
    ):  # fmt: skip
        _positive(errors, f"train.{name}", getattr(t, name))
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
    from mcrs.experiment.threads import cpu_count, threads_problem

    problem = threads_problem(cfg.threads, cpu_count())
    if problem:
        errors.append(f"threads={cfg.threads}: {problem}")
    if deep and not errors and env_config is not None:  # sizes are sane: has this machine what it needs?
        from mcrs.experiment.resources import resource_errors

        errors += resource_errors(cfg, env_config)
    return errors, env_config


def _memory_errors(cfg: Config, env_config: EnvConfig | None) -> list[str]:
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
    if mem.enabled and not errors and env_config is not None:
        errors += _embedding_fit_errors(cfg, env_config)
    return errors


def _embedding_fit_errors(cfg: Config, env_config: EnvConfig) -> list[str]:
    """Build the embedding once (cheap): one that does not fit the map is refused before any compute."""
    from mcrs.experiment.episodic import build_embedding  # here: it imports the models

    try:
        build_embedding(cfg, env_config)
    except ValueError as error:
        return [
            f"algo.memory.embedding={str(cfg.algo.memory.embedding)!r} does not fit {env_config.name}: {error}"
        ]
    return []


def validate(cfg: Config | DictConfig) -> EnvConfig:
    """Raise :class:`ConfigError` listing every problem of ``cfg``; return the env config it runs on."""
    errors, env_config = _problems(as_typed(cfg))
    if errors:
        raise ConfigError("invalid config:\n  - " + "\n  - ".join(errors))
    assert env_config is not None
    return env_config


def as_typed(cfg: Config | DictConfig) -> Config:
    """The typed :class:`Config` of a composed ``DictConfig`` (a :class:`Config` is returned as it is)."""
    if isinstance(cfg, Config):
        return cfg
    try:
        typed = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(Config), cfg))
    except OmegaConfBaseException as error:
        key = getattr(error, "full_key", None)
        first = (str(error).strip().splitlines() or [type(error).__name__])[0]
        raise ConfigError(f"invalid config: {key + ': ' if key else ''}{first}") from None
    given = _keys(OmegaConf.to_container(cfg, resolve=False))
    unknown = sorted(given - _keys(OmegaConf.to_container(OmegaConf.structured(typed), resolve=False)))
    if unknown:  # a key forced past the schema (``+env.widht=3``): to_object would drop it silently
        raise ConfigError(f"invalid config: unknown field(s) {', '.join(unknown)}: no schema has them")
    return typed


def _keys(tree: Any, prefix: str = "") -> set[str]:
    """The dotted keys of a nested dict (lists are leaves)."""
    if not isinstance(tree, dict):
        return {prefix[:-1]} if prefix else set()
    keys: set[str] = set()
    for key, value in tree.items():
        keys |= _keys(value, f"{prefix}{key}.")
    return keys


def as_dictconfig(cfg: Config | DictConfig) -> DictConfig:
    """The config as an OmegaConf node (for YAML and for Hydra-style access)."""
    return cfg if isinstance(cfg, DictConfig) else OmegaConf.structured(cfg)


def to_container(cfg: Config | DictConfig) -> dict[str, Any]:
    """A plain, resolved dict of the config, choices as strings (checkpoints, loggers, fingerprints)."""
    return OmegaConf.to_container(as_dictconfig(cfg), resolve=True, enum_to_str=True)


def compose(*overrides: str) -> Config:
    """The typed config ``mcrs-train <overrides>`` would run, composed from the packaged presets
    (``compose("algo=qmix", "env=map20", "train.total_env_steps=100000")``).

    A bad override raises :class:`ConfigError` with the line ``mcrs-train`` prints for it
    (``env.comm_rage: unknown key; the keys of env (closest first): comm_range, ...``)."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.errors import HydraException

    from mcrs.experiment.cli import describe

    register_configs()
    try:
        with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
            cfg = hydra_compose(config_name="config", overrides=list(overrides))
    except (HydraException, OmegaConfBaseException) as error:
        raise ConfigError(describe(error)) from None
    return as_typed(cfg)
