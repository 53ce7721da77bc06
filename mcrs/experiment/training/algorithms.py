"""Algorithms: what each value-factorisation algorithm brings to the one training loop, chosen from
``config.algo``.

An :class:`Algorithm` builds the parts that differ: the mixer, EMU's incentive, the TD loss, the
:class:`Learner` around them, and the callbacks (EMC's curiosity, the episodic memory) that write the keys the
loss reads. The built-in algorithms (``conf/algo/*.yaml``) differ only in their config nodes. An algorithm of
one's own subclasses it, overrides the parts it changes, declares its settings as an :attr:`Algorithm.Options`
dataclass (set through ``algo.options``, so they are checked, saved and fingerprinted) and is registered under
an ``algo.name``, or installed in the entry-point group ``mcrs.algorithms``::

    @register_algorithm("clipped_qmix")
    class ClippedQMIX(Algorithm):
        @dataclass
        class Options:
            clip: float = 10.0

        def loss(self, agent, mixer):
            return ClippedLoss(..., clip=self.options.clip)

    Experiment(compose("algo=qmix", "algo.name=clipped_qmix", "+algo.options.clip=5"), "outputs/run").run()
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import fields, is_dataclass, replace
from importlib.metadata import entry_points
from typing import Any, ClassVar

import torch
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException
from torch import nn

from mcrs.env.config import EnvConfig
from mcrs.experiment.schema import (
    ENTRY_POINT_GROUP,
    AlgoConfig,
    Config,
    ConfigError,
    ModelConfig,
    TrainConfig,
)
from mcrs.experiment.training.callbacks import Callback, CuriosityCallback
from mcrs.experiment.training.episodic import EpisodicMemoryCallback
from mcrs.experiment.training.learner import Learner, build_loss, build_mixer
from mcrs.experiment.training.task import Task
from mcrs.experiment.util.messages import listing
from mcrs.objectives import ValueFactorisationLoss
from mcrs.objectives.incentive import Incentive, make_incentive

__all__ = [
    "ALGORITHMS",
    "BUILT_IN",
    "ENTRY_POINT_GROUP",
    "Algorithm",
    "UnregisteredAlgorithm",
    "algorithm_class",
    "algorithm_for",
    "register_algorithm",
    "register_installed",
    "unregistered",
]


class Algorithm:
    """The parts of a value-factorisation algorithm, read from its ``algo`` config node. The experiment calls
    :meth:`learner` before :meth:`callbacks`, so the networks draw their initial weights in that order."""

    #: The algorithm's own settings: a dataclass whose fields ``algo.options`` sets, read into
    #: :attr:`options` (None: the algorithm takes none, and ``algo.options`` must be empty).
    Options: ClassVar[type | None] = None

    def __init__(self, algo: AlgoConfig) -> None:
        self.algo = algo
        self.options = self.read_options(algo)
        self.incentive = self.make_incentive()

    @classmethod
    def read_options(cls, algo: AlgoConfig) -> Any:
        """``algo.options`` as an :attr:`Options` instance with defaults filled in (None without
        :attr:`Options`); a bad key or value is a :class:`ConfigError` naming it."""
        given = dict(algo.options or {})
        if cls.Options is None:
            if given:
                key = next(iter(given))
                raise ConfigError(
                    f"algo.options.{key}: {cls.__name__} (algo.name={algo.name}) takes no options"
                    + ("" if str(algo.name) in ALGORITHMS else f" ({unregistered(str(algo.name))})")
                )
            return None
        known = [f.name for f in fields(cls.Options)]
        unknown = [key for key in given if key not in known]
        if unknown:
            raise ConfigError(
                f"algo.options.{unknown[0]}: not a setting of {cls.__name__} (algo.name={algo.name}); "
                f"its settings{listing(str(unknown[0]), known)}"
            )
        try:
            return OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(cls.Options), given))
        except OmegaConfBaseException as error:
            key = str(getattr(error, "full_key", None) or "?")
            value = f"={given[key]!r}" if key in given else ""
            first = (str(error).strip().splitlines() or [type(error).__name__])[0]
            raise ConfigError(f"algo.options.{key}{value}: {first}") from None

    @classmethod
    def with_options(cls, algo: AlgoConfig) -> AlgoConfig:
        """``algo`` with every setting of this algorithm in ``algo.options``, as ``config.yaml`` and the
        fingerprint hold it."""
        options = cls.read_options(algo)
        values = (
            {} if options is None else OmegaConf.to_container(OmegaConf.structured(options), enum_to_str=True)
        )
        return replace(algo, options=values)

    def make_incentive(self) -> Incentive:
        """EMU's incentive strategy (``algo.incentive``, ``algo.incentive_threshold``)."""
        return make_incentive(str(self.algo.incentive), self.algo.incentive_threshold)

    def mixer(self, task: Task) -> nn.Module:
        """The mixing network over the task's state (``algo.mixer``)."""
        return build_mixer(self.algo, task)

    def loss(self, agent: nn.Module, mixer: nn.Module) -> ValueFactorisationLoss:
        """The TD loss over the agent and this mixer; return a subclass of :class:`ValueFactorisationLoss` to
        change the target or the TD error."""
        return build_loss(self.algo, agent, mixer, self.incentive)

    def learner(
        self, model: ModelConfig, train: TrainConfig, env_config: EnvConfig | Task, device: torch.device
    ) -> Learner:
        """The agent, this mixer and this loss, with the optimiser and the target updates."""
        return Learner(
            self.algo,
            model,
            train,
            env_config,
            device,
            mixer=self.mixer,
            incentive=self.incentive,
            loss=self.loss,
        )

    def callbacks(
        self, config: Config, env_config: EnvConfig, learner: Learner, device: torch.device
    ) -> list[Callback]:
        """EMC's curiosity (``algo.curiosity_scale > 0``) and the episodic memory (``algo.memory.enabled``)."""
        callbacks: list[Callback] = []
        if self.algo.curiosity_scale > 0:
            callbacks.append(CuriosityCallback(config, learner.agent))
        if self.algo.memory.enabled:
            callbacks.append(EpisodicMemoryCallback(config, env_config, device, incentive=self.incentive))
        return callbacks

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.algo.name}: mixer={self.algo.mixer}, incentive={self.incentive})"


#: The presets of ``conf/algo/``: all the built-in :class:`Algorithm`, set apart by their config nodes.
BUILT_IN = ("qmix", "vdn", "qplex", "semu", "cnn_semu", "emc", "emu", "emu_370", "emu_change")

#: ``algo.name`` -> its :class:`Algorithm` class (:func:`register_algorithm` adds to it).
ALGORITHMS: dict[str, type[Algorithm]] = dict.fromkeys(BUILT_IN, Algorithm)


def register_algorithm(
    name: str, algorithm: type[Algorithm] | None = None, *, replace: bool = False
) -> Callable[[type[Algorithm]], type[Algorithm]] | type[Algorithm]:
    """Register an :class:`Algorithm` subclass under ``algo.name`` ``name``; without ``algorithm``, a class
    decorator. A name taken by another class needs ``replace=True``; the same class, or its redefinition in a
    notebook, replaces it."""
    if not isinstance(name, str):  # @register_algorithm without its name
        raise TypeError(
            f"register_algorithm: the first argument is the algo.name (a str), got {name!r}: write "
            '@register_algorithm("my_algo")'
        )

    def add(cls: type[Algorithm]) -> type[Algorithm]:
        if not (isinstance(cls, type) and issubclass(cls, Algorithm)):
            raise TypeError(f"register_algorithm({name!r}): expected an Algorithm subclass, got {cls!r}")
        if cls.Options is not None:
            check_options_class(name, cls)
        taken = ALGORITHMS.get(name)
        redefined = taken is not None and (taken.__module__, taken.__qualname__) == (
            cls.__module__,
            cls.__qualname__,
        )
        if taken is not None and not (replace or redefined):
            raise ValueError(
                f"algorithm {name!r} is already registered ({ALGORITHMS[name].__name__}); pass replace=True "
                "to replace it"
            )
        ALGORITHMS[name] = cls
        return cls

    return add if algorithm is None else add(algorithm)


#: The types an :attr:`Algorithm.Options` field may have: what a run's ``config.yaml`` holds as it is.
PLAIN = (str, int, float, bool, type(None), list, dict)


def check_options_class(name: str, cls: type[Algorithm]) -> None:
    """Raise a TypeError unless ``cls.Options`` is a dataclass OmegaConf can check with plain values (or
    enums), which a run's ``config.yaml`` can hold."""
    where = f"register_algorithm({name!r}): {cls.__name__}.Options"
    if not (isinstance(cls.Options, type) and is_dataclass(cls.Options)):
        raise TypeError(f"{where} must be a dataclass class")
    try:
        defaults = OmegaConf.to_container(OmegaConf.structured(cls.Options), enum_to_str=True)
    except OmegaConfBaseException as error:
        first = (str(error).strip().splitlines() or [type(error).__name__])[0]
        raise TypeError(f"{where}: {first}") from None
    for key, value in _leaves(defaults):
        if not isinstance(value, PLAIN):
            raise TypeError(
                f"{where}.{key}: a {type(value).__name__} is not a plain config value (str, int, float, bool, "
                "an Enum, or lists and dicts of them): a run's config.yaml could not hold it"
            )


def _leaves(tree: Any, prefix: str = "") -> list[tuple[str, Any]]:
    if isinstance(tree, dict):
        return [leaf for k, v in tree.items() for leaf in _leaves(v, f"{prefix}{k}.")]
    if isinstance(tree, list):
        return [leaf for k, v in enumerate(tree) for leaf in _leaves(v, f"{prefix}{k}.")]
    return [(prefix[:-1], tree)]


def algorithm_class(algo: AlgoConfig) -> type[Algorithm]:
    """The class registered or installed under ``algo.name``, else the built-in :class:`Algorithm`; the one
    place that reads ``algo.name``."""
    name = str(algo.name)
    if name not in ALGORITHMS:
        register_installed(name)
    return ALGORITHMS.get(name, Algorithm)


def algorithm_for(algo: AlgoConfig) -> Algorithm:
    """The algorithm of an ``algo`` config node, built from it."""
    return algorithm_class(algo)(algo)


class UnregisteredAlgorithm(UserWarning):
    """``algo.name`` names no registered algorithm, so the run trains the built-in one its knobs describe."""


def unregistered(name: str, what: str = "the built-in Algorithm") -> str:
    """What an ``algo.name`` nobody registered gets, and the names that are registered."""
    return f"algo.name={name} is not a registered algorithm: {what} (registered: {', '.join(ALGORITHMS)})"


def register_installed(name: str) -> bool:
    """Register the algorithm an installed package names ``name`` in :data:`ENTRY_POINT_GROUP`; False when
    none does. A broken entry point is a :class:`ConfigError`."""
    for entry in entry_points(group=ENTRY_POINT_GROUP, name=name):
        where = f"algo.name={name}: the entry point {entry.value!r} of {getattr(entry.dist, 'name', '?')}"
        try:
            algorithm = entry.load()
        except Exception as error:  # an installed plugin's own import error, said in one line
            first = (str(error).strip().splitlines() or [type(error).__name__])[0]
            raise ConfigError(f"{where} cannot be loaded: {type(error).__name__}: {first}") from None
        if not (isinstance(algorithm, type) and issubclass(algorithm, Algorithm)):
            raise ConfigError(f"{where} is {algorithm!r}, not an Algorithm subclass")
        try:
            register_algorithm(name, algorithm)
        except TypeError as error:  # its Options class: said as the plugin's problem, in one line
            raise ConfigError(f"{where}: {error}") from None
        return True
    return False
