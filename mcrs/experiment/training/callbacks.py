"""Callbacks: how an algorithm adds to the training loop without branching it (BenchMARL's shape).

The :class:`~mcrs.experiment.training.trainer.Experiment` calls every callback's hooks in order:

    on_setup(experiment)                 once, after everything is built (before a checkpoint is loaded)
    on_batch_collected(batch, ids)       after each collection: the episodes ``[E, T]`` and their ids ``[E]``
    on_train_batch(batch, env_steps)     before each learner update: may add keys the loss reads (the one
                                         way an algorithm adds to the batch: the memory's memory_return,
                                         memory_hit, memory_ratio; the curiosity's intrinsic_reward)
    on_evaluation_end(metrics)           after each greedy evaluation
    statistics()                         at each log row: scalars to log (``memory/...``)
    state_dict() / load_state_dict()     in every checkpoint, under ``callbacks/<name>``

Hooks return scalars to log (averaged over the log interval), or nothing; ``name`` keys the checkpoint state and the
``time/<name>_s`` timer. The episodic memory (SEMU, CNN-SEMU, EMU, EMC's buffer) is
:class:`~mcrs.experiment.training.episodic.EpisodicMemoryCallback`; EMC's curiosity is :class:`CuriosityCallback`;
the run's :class:`~mcrs.experiment.training.algorithms.Algorithm` builds the ones its ``algo`` config asks for. A
user's own callback (a scheduler, an extra logger) is passed as ``Experiment(..., callbacks=[...])``.
"""

from __future__ import annotations

import numbers
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import torch
from tensordict import TensorDictBase

from mcrs.experiment.schema import Config
from mcrs.experiment.training.learner import make_optimizer
from mcrs.experiment.util.messages import ranked
from mcrs.objectives.curiosity import EMCCuriosity

if TYPE_CHECKING:
    from torchrl.data import ReplayBuffer

    from mcrs.env.config import EnvConfig
    from mcrs.experiment.run.counters import Counters
    from mcrs.experiment.training.learner import Learner

Scalars = dict[str, float | torch.Tensor]


class ExperimentView(Protocol):
    """What a callback sees of the :class:`~mcrs.experiment.training.trainer.Experiment` that runs it.

    A Protocol, so that callbacks depend on the experiment's interface and not on the trainer module, which
    imports the callbacks (tests/test_layering.py refuses import cycles between modules)."""

    config: Config
    env_config: EnvConfig
    run_dir: Path
    device: torch.device
    counters: Counters  # env_steps, episodes, updates, ... (mcrs.experiment.run.counters)
    learner: Learner
    replay: ReplayBuffer  # the episode replay (batches reach callbacks through on_train_batch)
    last_eval: dict[str, float]  # the latest greedy evaluation's means (empty before the first)

    def evaluate(self) -> dict[str, float]: ...


#: The hooks the experiment calls (module docstring); a subclass's other ``on_*`` method is refused.
HOOKS = ("on_setup", "on_batch_collected", "on_train_batch", "on_evaluation_end")


def hook_scalars(callback: Callback, hook: str, returned: Any) -> Scalars:
    """What a hook returned, as scalars to log: nothing (None) is none; anything but a mapping of names to
    numbers or one-element tensors is a TypeError naming the callback, the hook and the key."""
    if returned is None:
        return {}
    where = f"callback {callback.name!r} ({type(callback).__name__}.{hook})"
    if not isinstance(returned, Mapping):
        raise TypeError(
            f"{where} returned a {type(returned).__name__}: return a dict of scalars to log "
            "(name -> number or one-element tensor), or nothing"
        )
    for key, value in returned.items():
        scalar = value.numel() == 1 if isinstance(value, torch.Tensor) else isinstance(value, numbers.Real)
        if not isinstance(key, str) or not scalar:
            raise TypeError(
                f"{where} returned {key!r}: {type(value).__name__} {value!r:.60}: a logged value is a "
                "number or a one-element tensor, under a string name"
            )
    return returned


class Callback:
    """A no-op callback; subclasses override the hooks they need.

    ``name`` keys the callback's checkpoint state and timer. A subclass that sets none is named after its
    class (one of a named callback keeps that name: it stands in for it), so two callbacks of one's own
    never share (or take over) each other's saved state."""

    name: str = "callback"
    _named_after_class = False  # the name was given by __init_subclass__, not by the class

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        for attr in cls.__dict__:  # a misspelt hook would never be called: refused where it is defined
            if attr.startswith("on_") and attr not in HOOKS:
                raise TypeError(
                    f"{cls.__name__}.{attr}: not a Callback hook (a method named on_* is one); the hooks "
                    f"(closest first): {', '.join(ranked(attr, list(HOOKS)))}"
                )
        if "name" in cls.__dict__:
            cls._named_after_class = False
        elif cls.name == Callback.name or cls._named_after_class:
            cls.name, cls._named_after_class = cls.__name__, True

    def on_setup(self, experiment: ExperimentView) -> None:
        """Called once the experiment is built; keep a reference if a hook needs it."""
        self.experiment = experiment

    def on_batch_collected(self, batch: TensorDictBase, episode_ids: torch.Tensor) -> Scalars:
        """New whole episodes ``[E, T]`` (the collector's layout) with their ids ``[E]``."""
        return {}

    def on_train_batch(self, batch: TensorDictBase, env_steps: int) -> Scalars:
        """A sampled batch of episodes ``[B, T+1]`` before the learner's update; may set keys on it."""
        return {}

    def on_evaluation_end(self, metrics: dict[str, float]) -> None:
        """The greedy evaluation's mean metrics (``episode_reward``, ...)."""

    def statistics(self) -> Scalars:
        """Scalars to log with each train row (state of the callback, not averaged)."""
        return {}

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`'s output."""


class CuriosityCallback(Callback):
    """EMC's curiosity: before each update, trains its VDN learner and predictor on the sampled batch and
    sets ``intrinsic_reward`` on it, which the TD loss adds to its target (its documented key)."""

    name = "curiosity"

    def __init__(self, config: Config, agent: torch.nn.Module) -> None:
        a, t = config.algo, config.train
        self.curiosity = EMCCuriosity(
            agent,
            gamma=a.gamma,
            scale=a.curiosity_scale,
            decay_rate=a.curiosity_decay_rate,
            decay_cycle=a.curiosity_decay_cycle,
            tau=a.curiosity_tau,
            grad_clip=t.grad_clip,
            make_optimizer=lambda params: make_optimizer(params, t),
        )

    def on_train_batch(self, batch: TensorDictBase, env_steps: int) -> Scalars:
        self.curiosity.set_env_steps(env_steps)
        intrinsic, stats = self.curiosity.update(batch, env_steps)
        batch.set("intrinsic_reward", intrinsic)
        return {f"train/{k}": v for k, v in stats.items()}

    def state_dict(self) -> dict[str, Any]:
        return self.curiosity.state_dict_all()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.curiosity.load_state_dict_all(state)


class UnreadBatchKey(UserWarning):
    """A callback set a key on the training batch that the built-in loss does not read (a misspelt
    ``intrinsic_rewards``): the run goes on, as if the callback had set nothing."""


def unread_batch_keys(callback: Callback, added: set, loss: Any) -> str | None:
    """What to say when ``callback``'s ``on_train_batch`` added ``added`` (nested keys) to the batch and the
    loss, the built-in :class:`~mcrs.objectives.ValueFactorisationLoss`, reads none of some of them; None
    otherwise (a loss of one's own may read any key: nothing is said)."""
    from mcrs.objectives import ValueFactorisationLoss

    if type(loss) is not ValueFactorisationLoss:
        return None
    read = {key if isinstance(key, str) else tuple(key) for key in vars(loss.tensor_keys).values()}
    unread = sorted((key for key in added if key not in read), key=str)
    if not unread:
        return None
    names = sorted(key for key in read if isinstance(key, str))
    closest = ", ".join(ranked(str(unread[0]), names)[:3])
    return (
        f"callback {callback.name!r} ({type(callback).__name__}.on_train_batch) set {', '.join(map(repr, unread))} "
        f"on the training batch, which the loss does not read (closest it reads: {closest})"
    )


def append_scalar(stats: dict[str, list[torch.Tensor]], key: str, value: float | torch.Tensor) -> None:
    """Collect a hook's scalar for the next log row (where it is averaged)."""
    stats.setdefault(key, []).append(value if isinstance(value, torch.Tensor) else torch.tensor(value))


def check_names(callbacks: list[Callback]) -> None:
    """Every callback is a :class:`Callback` instance, and callbacks key their checkpoint state and timers
    by name: two with one name would collide."""
    for k, callback in enumerate(callbacks):
        if isinstance(callback, type) and issubclass(callback, Callback):
            raise TypeError(
                f"callbacks[{k}]: the class {callback.__name__}, not an instance: pass {callback.__name__}()"
            )
        if not isinstance(callback, Callback):
            raise TypeError(
                f"callbacks[{k}]: expected an mcrs.Callback instance, got {type(callback).__name__}"
            )
    names = [cb.name for cb in callbacks]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise ValueError(f"callbacks must have distinct names (they key checkpoints), repeated: {duplicates}")
