"""Callbacks: how an algorithm adds to the training loop without branching it, as in BenchMARL.

The :class:`~mcrs.experiment.training.trainer.Experiment` calls every callback's hooks in order::

    on_setup(experiment)                 once, after everything is built, before a checkpoint is loaded
    on_batch_collected(batch, ids)       after each collection: the episodes [E, T] and their ids [E]
    on_train_batch(batch, env_steps)     before each learner update; may add keys the loss reads
    on_evaluation_end(metrics)           after each greedy evaluation
    statistics()                         at each log row: scalars to log (memory/...)
    state_dict() / load_state_dict()     in every checkpoint, under callbacks/<name>

Hooks return scalars to log, averaged over the log interval, or nothing. ``name`` keys the checkpoint state
and the ``time/<name>_s`` timer. A user's own callback is passed as ``Experiment(..., callbacks=[...])``.
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
from mcrs.objectives import ValueFactorisationLoss
from mcrs.objectives.curiosity import EMCCuriosity

if TYPE_CHECKING:
    from torchrl.data import ReplayBuffer

    from mcrs.env.config import EnvConfig
    from mcrs.experiment.run.counters import Counters
    from mcrs.experiment.training.learner import Learner

Scalars = dict[str, float | torch.Tensor]


class ExperimentView(Protocol):
    """What a callback sees of the experiment that runs it; a Protocol, since the trainer imports this module."""

    config: Config
    env_config: EnvConfig
    run_dir: Path
    device: torch.device
    counters: Counters  # env_steps, episodes, updates, ... (mcrs.experiment.run.counters)
    learner: Learner
    replay: ReplayBuffer  # the episode replay (batches reach callbacks through on_train_batch)
    last_eval: dict[str, float]  # the latest greedy evaluation's means (empty before the first)

    def evaluate(self) -> dict[str, float]: ...


#: The hooks the experiment calls; a subclass's other ``on_*`` method is refused.
HOOKS = ("on_setup", "on_batch_collected", "on_train_batch", "on_evaluation_end")


def hook_scalars(callback: Callback, hook: str, returned: Any) -> Scalars:
    """What a hook returned, as scalars to log; anything but names mapped to numbers or one-element tensors is
    a TypeError."""
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
    """A no-op callback; subclasses override the hooks they need. A subclass without its own ``name`` is named
    after its class, so that two callbacks never share saved state."""

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
        """Called once the experiment is built; keeps a reference to it."""
        self.experiment = experiment

    def on_batch_collected(self, batch: TensorDictBase, episode_ids: torch.Tensor) -> Scalars:
        """New whole episodes ``[E, T]`` with their ids ``[E]``."""
        return {}

    def on_train_batch(self, batch: TensorDictBase, env_steps: int) -> Scalars:
        """A sampled batch of episodes ``[B, T+1]`` before the learner's update; may set keys on it."""
        return {}

    def on_evaluation_end(self, metrics: dict[str, float]) -> None:
        """The greedy evaluation's mean metrics."""

    def statistics(self) -> Scalars:
        """Scalars to log with each train row, not averaged."""
        return {}

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`'s output."""


class CuriosityCallback(Callback):
    """EMC's curiosity: before each update it trains its VDN learner and predictor on the batch and sets
    ``intrinsic_reward``, which the TD loss adds to its target."""

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
    """A callback set a key on the training batch that the built-in loss does not read, such as a misspelt
    ``intrinsic_rewards``."""


def unread_batch_keys(callback: Callback, added: set, loss: Any) -> str | None:
    """The warning when ``callback`` added batch keys (``added``) that the built-in loss does not read, else
    None; a loss of one's own may read any key."""
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
    """Collect a hook's scalar for the next log row, where it is averaged."""
    stats.setdefault(key, []).append(value if isinstance(value, torch.Tensor) else torch.tensor(value))


def check_names(callbacks: list[Callback]) -> None:
    """Check that every callback is a :class:`Callback` instance and that their names, which key checkpoints
    and timers, are distinct."""
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
