"""The typed schemas of the training config, registered in Hydra's ConfigStore, and their conversions.

One typed node per concept: ``env`` (the scenario, :class:`mcrs.env.ScenarioConfig`), ``algo`` (with
``algo.memory``), ``model``, ``train``, ``logger``; choices are enums over the lists of :mod:`mcrs.choices`,
so Hydra refuses unknown keys, wrong types and unknown choices while composing. Each node checks its own
values (``errors()``, one message per problem, each naming the field by its path in the config). The rules
that span nodes (the memory against the scenario, the labels that name run directories) and those of the
machine (threads, device) are :func:`mcrs.experiment.config.validate`'s: the machine's need runtime
modules, and those modules need these schemas, so the schemas import none of them (tests/test_layering.py
refuses import cycles between modules). Import the names from :mod:`mcrs.experiment.config`, which
re-exports them.
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

from mcrs.choices import (
    COLLECTORS,
    DELTA_RULES,
    EMBEDDINGS,
    INCENTIVES,
    LOGGER_BACKENDS,
    MIXERS,
    MODEL_NAMES,
    OPTIMIZERS,
    SHAPES,
    TIME_LIMITS,
    WANDB_MODES,
)
from mcrs.env.config import FieldsOnly, ScenarioConfig


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
Optimizer = _choices("Optimizer", OPTIMIZERS)
LoggerBackend = _choices("LoggerBackend", LOGGER_BACKENDS)
WandbMode = _choices("WandbMode", WANDB_MODES)
ModelName = _choices("ModelName", MODEL_NAMES)
Collector = _choices("Collector", COLLECTORS)
Embedding = _choices("Embedding", EMBEDDINGS)  # random (EMC) | fc (SEMU) | cnn (CNN-SEMU)
Incentive = _choices("Incentive", INCENTIVES)
DeltaRule = _choices("DeltaRule", DELTA_RULES)
Neighbourhood = _choices("Neighbourhood", SHAPES)
TimeLimit = _choices("TimeLimit", TIME_LIMITS)
MAX_SEED = 2**63 - 1  # batch seeds are taken modulo 2**63; torch's generator takes 64-bit seeds
MAX_MEMORY_CAPACITY = 2**31 - 1  # slots of the episodic memory are int32
MAX_STEPS_LIMIT = 2**15  # the episodic memory stores an entry's step as int16 (mcrs.memory.episodic)
MAX_EVAL_EPISODES = 100_000  # mcrs-eval keeps every episode's metrics; more is several runs with other seeds
MAX_LR = 1.0  # learning rates above this are refused: no optimiser here takes a step beyond the parameters
# The Hydra configs, the one CONFIG_DIR of every command and tool: mcrs/conf links to the repo's conf/ (and is
# copied into wheels as package data). An absolute directory, because Hydra's pkg:// lookup of "mcrs.conf"
# needs an __init__.py that conf/ lacks.
CONFIG_DIR = str(Path(__file__).resolve().parents[1] / "conf")
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


def _positive(errors: list[str], name: str, value: float, allow_zero: bool = False) -> None:
    """Add a message when ``value`` is not > 0 (>= 0 with ``allow_zero``) or not finite."""
    ok = value >= 0 if allow_zero else value > 0
    if not ok or (isinstance(value, float) and not math.isfinite(value)):
        errors.append(f"{name}={value}: must be {'>= 0' if allow_zero else '> 0'}")


def _fraction(errors: list[str], name: str, value: float) -> None:
    """Add a message when ``value`` is not in [0, 1]."""
    if not 0.0 <= value <= 1.0:
        errors.append(f"{name}={value}: must be in [0, 1]")


def _choice(errors: list[str], name: str, value: Any, allowed: type[Choice]) -> None:
    """Add a message when a choice of a :class:`Config` built in Python is not one of ``allowed``.

    OmegaConf never sees such a config (``as_typed`` returns it as it is); a composed config's choices were
    refused by OmegaConf's structured schema already. OmegaConf's own check of such an instance
    (``OmegaConf.structured``) stops at the first bad field and names it without its node (``mixer``, not
    ``algo.mixer``), so every bad choice is named here, in full."""
    values = [member.value for member in allowed]
    if str(value) not in values:
        errors.append(f"{name}={str(value)!r}: allowed values are {', '.join(values)}")


@dataclass
class MemoryConfig(FieldsOnly):
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

    def errors(self) -> list[str]:
        """The problems of these fields, one message each (``algo.memory.<field>=<value>: ...``). Whether
        the memory fits the scenario (its steps, its counts) is :func:`mcrs.experiment.config.validate`'s."""
        errors: list[str] = []
        _choice(errors, "algo.memory.embedding", self.embedding, Embedding)
        _choice(errors, "algo.memory.delta_rule", self.delta_rule, DeltaRule)
        _choice(errors, "algo.memory.neighbourhood", self.neighbourhood, Neighbourhood)
        if self.delta <= 0 or not math.isfinite(self.delta):
            errors.append(f"algo.memory.delta={self.delta}: must be > 0")
        if self.capacity < 1:
            errors.append(f"algo.memory.capacity={self.capacity}: must be >= 1 entry")
        elif self.capacity > MAX_MEMORY_CAPACITY:
            errors.append(f"algo.memory.capacity={self.capacity}: must be <= 2**31 - 1 entries (int32 slots)")
        for name in ("key_dim", "hidden_dim", "embedding_interval", "embedding_samples", "embedding_batch"):
            _positive(errors, f"algo.memory.{name}", getattr(self, name))
        _positive(errors, "algo.memory.embedding_lr", self.embedding_lr)
        lr = self.embedding_lr
        if math.isfinite(lr) and lr > MAX_LR:  # RMSprop's squared gradients overflow at 1e300
            errors.append(
                f"algo.memory.embedding_lr={lr}: must be <= {MAX_LR:g} (a larger step diverges at once)"
            )
        _positive(errors, "algo.memory.state_weight", self.state_weight, allow_zero=True)
        if not self.embedding_grad_clip > 0:
            errors.append(
                f"algo.memory.embedding_grad_clip={self.embedding_grad_clip}: must be > 0 (inf: no clipping)"
            )
        channels = self.cnn_channels
        if len(channels) != 3 or any(c < 1 for c in channels):
            errors.append(f"algo.memory.cnn_channels={list(channels)}: must be 3 positive channel counts")
        if self.embedding_batch > self.embedding_samples > 0:
            errors.append(
                f"algo.memory.embedding_batch={self.embedding_batch} > algo.memory.embedding_samples="
                f"{self.embedding_samples}: each training of the embedding draws its batches from the samples"
            )
        if self.enabled and self.key_dim > 8:
            errors.append(
                f"algo.memory.key_dim={self.key_dim}: at most 8 (each look-up checks 2^key_dim grid cells)"
            )
        return errors


@dataclass
class AlgoConfig(FieldsOnly):
    """The value-factorisation algorithm: which mixer, the TD target and the episodic-memory terms."""

    name: str = "qmix"  # label of the algorithm (run names, reports)
    mixer: Mixer = Mixer.qmix
    mixing_embed_dim: int = 32  # QMIX mixing width
    hypernet_embed: int = 64  # hidden width of the hypernetworks (QMIX, QPLEX)
    hypernet_layers: int = 2  # QMIX hypernetwork depth: 1 (TorchRL) or 2 (pymarl)
    qplex_kernels: int = 4  # QPLEX attention heads of the advantage weights
    qplex_adv_layers: int = 1  # depth of QPLEX's advantage-weight extractors: 1 (SMAC setting) to 3
    gamma: float = 0.99
    # the TD targets' unit: the env's reward (and the memory's returns) times this; thresholds stay the env's
    reward_scale: float = 1.0
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
    # a registered or installed algorithm's own settings, checked against its Algorithm.Options dataclass
    # (mcrs.experiment.training.algorithms): +algo.options.<key>=<value>; a run's config.yaml holds all of them
    options: dict[str, Any] = field(default_factory=dict)

    def errors(self) -> list[str]:
        """The problems of these fields and of ``memory``'s, one message each (``algo.<field>=<value>: ...``).
        ``name`` is a label of run directories, checked with the others by
        :func:`mcrs.experiment.config.validate`; ``options`` are the algorithm's own to check."""
        errors: list[str] = []
        _choice(errors, "algo.mixer", self.mixer, Mixer)
        _choice(errors, "algo.time_limit", self.time_limit, TimeLimit)
        if self.hypernet_layers not in (1, 2):
            errors.append(f"algo.hypernet_layers={self.hypernet_layers}: allowed values are 1, 2")
        if self.qplex_adv_layers not in (1, 2, 3):
            errors.append(f"algo.qplex_adv_layers={self.qplex_adv_layers}: allowed values are 1, 2, 3")
        for name in ("mixing_embed_dim", "hypernet_embed", "qplex_kernels", "reward_scale"):
            _positive(errors, f"algo.{name}", getattr(self, name))
        for name in ("gamma", "td_lambda"):
            _fraction(errors, f"algo.{name}", getattr(self, name))
        _choice(errors, "algo.incentive", self.incentive, Incentive)
        if self.memory_weight < 0 or not math.isfinite(self.memory_weight):
            errors.append(f"algo.memory_weight={self.memory_weight}: must be >= 0 (lambda of eq. 32)")
        _positive(errors, "algo.curiosity_scale", self.curiosity_scale, allow_zero=True)
        _positive(errors, "algo.curiosity_decay_cycle", self.curiosity_decay_cycle)
        for name in ("curiosity_decay_rate", "curiosity_tau"):
            _fraction(errors, f"algo.{name}", getattr(self, name))
        uses_memory = self.memory_weight > 0 or str(self.incentive) != "none"
        if uses_memory and not self.memory.enabled:
            errors.append(
                f"algo.memory.enabled=false, but algo.memory_weight={self.memory_weight} and "
                f"algo.incentive={self.incentive!r} need the episodic memory: set algo.memory.enabled=true"
            )
        if not math.isfinite(self.incentive_threshold):
            errors.append(f"algo.incentive_threshold={self.incentive_threshold}: must be a finite return")
        return errors + self.memory.errors()


@dataclass
class ModelConfig(FieldsOnly):
    """The shared recurrent agent network."""

    name: ModelName = ModelName.gru
    hidden_dim: int = 64
    agent_id: bool = True  # one-hot agent id as input
    last_action: bool = True  # one-hot last action as input

    def errors(self) -> list[str]:
        """The problems of these fields, one message each (``model.<field>=<value>: ...``)."""
        errors: list[str] = []
        _choice(errors, "model.name", self.name, ModelName)
        _positive(errors, "model.hidden_dim", self.hidden_dim)
        return errors


@dataclass
class LoggerConfig(FieldsOnly):
    """Where metrics go (TorchRL loggers). Nothing leaves the machine unless wandb_mode=online."""

    backend: LoggerBackend = LoggerBackend.csv
    project: str = "mcrs"  # wandb project
    wandb_mode: WandbMode = WandbMode.offline
    log_interval: int = 2000  # env steps between train/ and time/ log rows (means over the interval)
    progress_bar: bool = True
    video: bool = False  # one greedy evaluation episode as a video at every evaluation (GIF; tb, wandb)

    def errors(self) -> list[str]:
        """The problems of these fields, one message each (``logger.<field>=<value>: ...``)."""
        errors: list[str] = []
        _choice(errors, "logger.backend", self.backend, LoggerBackend)
        _choice(errors, "logger.wandb_mode", self.wandb_mode, WandbMode)
        _positive(errors, "logger.log_interval", self.log_interval)
        if not str(self.project).strip():
            errors.append(f"logger.project={self.project!r}: must be a non-empty name")
        return errors


@dataclass
class TrainConfig(FieldsOnly):
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

    def errors(self) -> list[str]:
        """The problems of these fields, one message each (``train.<field>=<value>: ...``). Whether whole
        collector batches fit the run's length is the command line's check (``mcrs.train``)."""
        errors: list[str] = []
        _choice(errors, "train.optimizer", self.optimizer, Optimizer)
        for name in (
            "total_env_steps", "num_envs", "batch_episodes", "replay_episodes", "lr", "optim_eps",
            "grad_clip", "eps_anneal_steps", "target_update_episodes", "eval_interval", "eval_episodes",
            "checkpoint_interval",
        ):  # fmt: skip
            _positive(errors, f"train.{name}", getattr(self, name))
        if math.isfinite(self.lr) and self.lr > MAX_LR:  # RMSprop's squared gradients overflow at 1e300
            errors.append(f"train.lr={self.lr}: must be <= {MAX_LR:g} (a larger step diverges at once)")
        _positive(errors, "train.updates_per_episode", self.updates_per_episode, allow_zero=True)
        _positive(errors, "train.checkpoint_minutes", self.checkpoint_minutes, allow_zero=True)
        if self.keep_checkpoints < 0:
            errors.append(
                f"train.keep_checkpoints={self.keep_checkpoints}: must be >= 0 (0 keeps every weight file)"
            )
        for name in ("eps_start", "eps_end", "rmsprop_alpha"):
            _fraction(errors, f"train.{name}", getattr(self, name))
        if self.eps_end > self.eps_start:
            errors.append(
                f"train.eps_end={self.eps_end} > train.eps_start={self.eps_start}: epsilon only decays"
            )
        if self.replay_episodes < self.batch_episodes:
            errors.append(
                f"train.replay_episodes={self.replay_episodes} < train.batch_episodes={self.batch_episodes}: "
                "the buffer must hold a whole batch"
            )
        _choice(errors, "train.collector", self.collector, Collector)
        workers = self.collector_workers
        if workers < 1:
            errors.append(f"train.collector_workers={workers}: must be >= 1")
        elif str(self.collector) == "multiprocess" and self.num_envs % workers:
            errors.append(
                f"train.num_envs={self.num_envs} is not divisible by train.collector_workers={workers}: "
                "each worker collects the same number of whole episodes"
            )
        if not 0 <= self.eval_seed <= MAX_SEED:
            errors.append(f"train.eval_seed={self.eval_seed}: must be in [0, 2**63 - 1]")
        return errors


@dataclass
class Config(FieldsOnly):
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
    # the task, when not MCRS on env: {_target_: <module>.<Task class>, **its settings} (conf/task/, or what
    # Experiment(task=...) records); None: MCRS on env, and the key is left out of config.yaml and checkpoints
    task: dict[str, Any] | None = None


def register_configs() -> None:
    """Register the schemas (``config.yaml`` names ``mcrs_config`` in its defaults)."""
    cs = ConfigStore.instance()
    cs.store(name="mcrs_config", node=Config)


def as_typed(cfg: Config | DictConfig) -> Config:
    """The typed :class:`Config` of a composed ``DictConfig`` (a :class:`Config` is returned as it is)."""
    if isinstance(cfg, Config):
        return cfg
    given = _keys(OmegaConf.to_container(cfg, resolve=False))
    schema = _keys(OmegaConf.to_container(OmegaConf.structured(Config), resolve=False))
    unknown = sorted(k for k in given - schema if not k.startswith(FREE_FORM))
    if unknown:  # a key forced past the schema (``+env.widht=3``): no field would ever read it
        raise ConfigError(f"invalid config: unknown field(s) {', '.join(unknown)}: no schema has them")
    try:
        return OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(Config), cfg))
    except OmegaConfBaseException as error:
        key = getattr(error, "full_key", None)
        first = (str(error).strip().splitlines() or [type(error).__name__])[0]
        raise ConfigError(f"invalid config: {key + ': ' if key else ''}{first}") from None


#: The entry-point group in which installed packages name their algorithms (``algo.name`` -> class;
#: :mod:`mcrs.experiment.training.algorithms` loads them): here, so that a command can tell one is installed before
#: torch loads.
ENTRY_POINT_GROUP = "mcrs.algorithms"

#: The nodes whose keys no schema lists: an algorithm's own settings, checked by the algorithm
#: (:meth:`mcrs.experiment.training.algorithms.Algorithm.read_options`), and a task's, checked by its class
#: (:func:`mcrs.experiment.training.task.make_task`).
FREE_FORM = ("algo.options.", "task.")


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
    """A plain, resolved dict of the config, choices as strings (checkpoints, loggers, fingerprints). An
    MCRS run (``task`` None) has no ``task`` key: its files are what they were before tasks."""
    out = OmegaConf.to_container(as_dictconfig(cfg), resolve=True, enum_to_str=True)
    if out.get("task", 0) is None:
        del out["task"]
    return out
