"""A callback's mistakes are named where they are made: a misspelt hook when the class is defined, a hook
that returns something other than scalars when it returns it; a hook that returns nothing is fine."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from mcrs.experiment.config import compose
from mcrs.experiment.training.callbacks import HOOKS, Callback, UnreadBatchKey, hook_scalars
from mcrs.experiment.training.trainer import Experiment
from tests.train_helpers import TINY, TINY_MEMORY


def test_a_misspelt_hook_is_refused_when_the_class_is_defined() -> None:
    with pytest.raises(
        TypeError, match=r"^Late\.on_eval_end: not a Callback hook .* \(closest first\): on_evaluation_end,"
    ):

        class Late(Callback):
            def on_eval_end(self, metrics) -> None: ...

    class Fine(Callback):  # the hooks, and methods that are not hooks, are fine
        def on_evaluation_end(self, metrics) -> None: ...

        def helper(self) -> None: ...

    assert set(HOOKS) == {name for name in vars(Callback) if name.startswith("on_")}


class Returns(Callback):
    def __init__(self, value: object) -> None:
        self.value = value


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        ([1.0], r"callback 'Returns' \(Returns.statistics\) returned a list: return a dict of scalars"),
        ({"my/thing": "abc"}, r"returned 'my/thing': str 'abc': a logged value is a number"),
        ({"my/vector": torch.zeros(3)}, r"returned 'my/vector': Tensor"),
        ({3: 1.0}, r"returned 3: float 1.0: .* under a string name"),
    ],
)
def test_a_hook_that_returns_no_scalars_is_named(value: object, expected: str) -> None:
    with pytest.raises(TypeError, match=expected):
        hook_scalars(Returns(value), "statistics", value)


def test_hooks_may_return_nothing_or_scalars() -> None:
    assert hook_scalars(Returns(None), "on_train_batch", None) == {}
    scalars = {
        "a": 1,
        "b": 2.5,
        "c": torch.tensor(3.0),
        "d": torch.tensor([4.0]),
        "e": np.float32(5),
        "f": True,
    }
    assert hook_scalars(Returns(scalars), "on_train_batch", scalars) is scalars


class Quiet(Callback):
    """Every hook returns nothing: it only watches."""

    def __init__(self) -> None:
        self.calls = {"collected": 0, "train": 0, "statistics": 0}

    def on_batch_collected(self, batch, episode_ids):  # type: ignore[override]
        self.calls["collected"] += 1

    def on_train_batch(self, batch, env_steps):  # type: ignore[override]
        self.calls["train"] += 1

    def statistics(self):  # type: ignore[override]
        self.calls["statistics"] += 1


def test_a_run_with_hooks_that_return_nothing_trains(tmp_path: Path) -> None:
    quiet = Quiet()
    config = compose("algo=qmix", *TINY, "train.total_env_steps=40")
    Experiment(config, tmp_path / "run", callbacks=[quiet]).run()
    assert all(count > 0 for count in quiet.calls.values()), quiet.calls


class Misspelt(Callback):
    def on_train_batch(self, batch, env_steps):  # type: ignore[override]
        batch.set(
            "intrinsic_rewards", torch.zeros_like(batch.get("reward"))
        )  # the loss reads intrinsic_reward


class Spelt(Callback):
    def on_train_batch(self, batch, env_steps):  # type: ignore[override]
        batch.set("intrinsic_reward", torch.zeros_like(batch.get("reward")))


def test_a_batch_key_the_loss_never_reads_is_said_once(tmp_path: Path) -> None:
    config = compose("algo=qmix", *TINY, "train.total_env_steps=80")
    with pytest.warns(UnreadBatchKey) as said:
        Experiment(config, tmp_path / "misspelt", callbacks=[Misspelt()]).run()
    notes = [str(w.message) for w in said if w.category is UnreadBatchKey]
    assert len(notes) == 1, notes  # once: on the first update, not on every one
    assert notes[0].startswith(
        "callback 'Misspelt' (Misspelt.on_train_batch) set 'intrinsic_rewards' on the training batch, which the "
        "loss does not read (closest it reads: intrinsic_reward, "
    ), notes


@pytest.mark.parametrize(
    ("algo", "callbacks"),
    [
        ("qmix", [Spelt()]),
        ("emu", []),
        ("emc", []),
    ],  # a key it reads; the memory's and the curiosity's own keys
)
def test_the_keys_the_loss_reads_are_not_said(algo: str, callbacks: list[Callback], tmp_path: Path) -> None:
    config = compose(f"algo={algo}", *TINY, *TINY_MEMORY, "train.total_env_steps=80")
    with warnings.catch_warnings():
        warnings.simplefilter("error", UnreadBatchKey)
        Experiment(config, tmp_path / algo, callbacks=callbacks).run()
