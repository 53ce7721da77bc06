"""The Python API: ``Experiment`` built from a typed config, its callbacks, its state and checkpoint retention."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import torch

import mcrs
from mcrs.experiment.config import AlgoConfig, Config, compose
from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.training.algorithms import ALGORITHMS
from mcrs.experiment.training.callbacks import Callback, ExperimentView
from mcrs.experiment.training.learner import Learner
from mcrs.experiment.training.trainer import Experiment
from tests.train_helpers import TINY, TINY_MEMORY

pytestmark = pytest.mark.slow


class Recorder(Callback):
    """Counts every hook and keeps a number in its state, to see hooks run and state travel."""

    name = "recorder"

    def __init__(self) -> None:
        self.calls: list[str] = []
        self.collected_episodes = 0

    def on_batch_collected(self, batch, episode_ids) -> dict[str, float]:
        self.calls.append("collected")
        assert episode_ids.tolist() == list(
            range(self.collected_episodes, self.collected_episodes + len(batch))
        )
        self.collected_episodes += len(batch)
        return {"recorder/episodes": float(self.collected_episodes)}

    def on_train_batch(self, batch, env_steps: int) -> dict[str, float]:
        self.calls.append("train")
        batch.set("intrinsic_reward", torch.zeros_like(batch.get("reward")))  # a key the loss reads
        return {}

    def on_evaluation_end(self, metrics: dict[str, float]) -> None:
        assert "episode_reward" in metrics
        self.calls.append("evaluated")

    def state_dict(self) -> dict[str, Any]:
        return {"collected_episodes": self.collected_episodes}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.collected_episodes = state["collected_episodes"]


def tiny(*overrides: str) -> Config:
    return compose("algo=qmix", *TINY, *overrides)


def test_compose_gives_typed_nodes_and_the_experiment_runs_them(tmp_path: Path) -> None:
    config = tiny("train.total_env_steps=40")
    assert isinstance(config, Config) and isinstance(config.algo, AlgoConfig)
    assert str(config.algo.mixer) == "qmix" and config.env.name == "map10"
    recorder = Recorder()
    experiment = mcrs.Experiment(config, tmp_path / "run", callbacks=[recorder])  # the package's lazy name
    assert isinstance(experiment, Experiment) and mcrs.compose is compose
    assert experiment.env_config.num_envs == config.train.num_envs  # runtime fields from train/device
    result = experiment.run()
    assert set(result) >= {"episode_reward", "uncertainty"} and experiment.counters.env_steps >= 40
    evaluations = recorder.calls.count("evaluated")
    # Evaluating right after run() gives its last evaluation: no second row at that step, no second hook call.
    assert experiment.evaluate() == result
    assert recorder.calls.count("evaluated") == evaluations
    log = tmp_path / "run/logs/scalars/eval/episode_reward.csv"
    steps = [line.split(",")[0] for line in log.open()]
    assert len(steps) == len(set(steps)) == evaluations
    # A finished run resumed: its last evaluation is logged already, at this step.
    finished = mcrs.Experiment(config, tmp_path / "run", resume=True, callbacks=[Recorder()])
    assert finished.run() == result and finished.evaluate() == result
    assert [line.split(",")[0] for line in log.open()] == steps


def test_user_callback_hooks_run_and_its_state_is_checkpointed(tmp_path: Path) -> None:
    recorder = Recorder()
    Experiment(tiny("train.total_env_steps=80"), tmp_path / "run", callbacks=[recorder]).run()
    assert recorder.calls[0] == "evaluated" and "collected" in recorder.calls and "train" in recorder.calls
    assert recorder.calls.index("collected") < recorder.calls.index("train")  # episodes before updates
    state = ckpt.load(ckpt.checkpoint_path(tmp_path / "run"))
    assert state["callbacks"]["recorder"] == {"collected_episodes": recorder.collected_episodes}
    log = (tmp_path / "run" / "logs").rglob("*recorder*")
    assert any(True for _ in log), "the hook's scalars are logged"

    resumed_recorder = Recorder()
    resumed = Experiment(
        tiny("train.total_env_steps=120"), tmp_path / "run", resume=True, callbacks=[resumed_recorder]
    )
    assert resumed_recorder.collected_episodes == recorder.collected_episodes
    resumed.close()


class Stateless(Callback):
    name = "stateless"


class Unnamed(Recorder):
    """A callback of one's own that names itself after nothing: its class names it."""

    name = Callback.name


class FirstUnnamed(Callback):
    def state_dict(self) -> dict[str, Any]:
        return {"first": 1}


class SecondUnnamed(Callback):
    def load_state_dict(self, state: dict[str, Any]) -> None:
        raise AssertionError("another callback's state")


class ThirdUnnamed(FirstUnnamed):
    """An unnamed subclass of an unnamed callback: its own class names it too."""


class MyRecorder(Recorder):
    """A subclass of a named callback stands in for it: the name is kept."""


def test_a_callback_without_a_name_is_named_after_its_class(tmp_path: Path) -> None:
    assert (FirstUnnamed.name, SecondUnnamed.name, Stateless.name) == (
        "FirstUnnamed",
        "SecondUnnamed",
        "stateless",
    )
    assert (ThirdUnnamed.name, MyRecorder.name) == ("ThirdUnnamed", "recorder")
    assert Unnamed.name == "callback"  # set in the class body: kept (check_names refuses two such)
    Experiment(tiny("train.total_env_steps=40"), tmp_path / "run", callbacks=[FirstUnnamed()]).run()
    # Another unnamed callback does not take over the first one's saved state: the resume is refused.
    longer = tiny("train.total_env_steps=80")
    with pytest.raises(ckpt.CheckpointError, match="holds the state of the callback 'FirstUnnamed'"):
        Experiment(longer, tmp_path / "run", resume=True, callbacks=[SecondUnnamed()])
    with pytest.raises(ckpt.CheckpointError, match="holds the state of the callback 'FirstUnnamed'"):
        Experiment(longer, tmp_path / "run", resume=True, callbacks=[ThirdUnnamed()])


def test_a_resume_keeps_every_callback_with_state_and_admits_stateless_ones(tmp_path: Path) -> None:
    Experiment(tiny("train.total_env_steps=80"), tmp_path / "run", callbacks=[Recorder()]).run()
    longer = tiny("train.total_env_steps=120")
    # Dropping a callback whose state the checkpoint holds would lose it: refused, naming it.
    with pytest.raises(ckpt.CheckpointError, match="holds the state of the callback 'recorder'"):
        Experiment(longer, tmp_path / "run", resume=True)
    # A stateless callback may join a resumed run (API.md's resume adds one); one with state may not.
    Experiment(longer, tmp_path / "run", resume=True, callbacks=[Recorder(), Stateless()]).close()
    Experiment(tiny("train.total_env_steps=80"), tmp_path / "plain").run()
    with pytest.raises(ckpt.CheckpointError, match="no state for this run's 'recorder' callback"):
        Experiment(longer, tmp_path / "plain", resume=True, callbacks=[Recorder()])
    Experiment(longer, tmp_path / "plain", resume=True, callbacks=[Stateless()]).run()


def test_algorithm_callbacks_come_from_the_algo_config(tmp_path: Path) -> None:
    plain = Experiment(tiny(), tmp_path / "qmix")
    assert plain.callbacks == []
    promised = [*ExperimentView.__annotations__, "evaluate"]  # what callbacks are typed to see of it
    assert promised[:2] == ["config", "env_config"] and [n for n in promised if not hasattr(plain, n)] == []
    plain.close()
    emc = Experiment(compose("algo=emc", *TINY, *TINY_MEMORY), tmp_path / "emc")
    assert [cb.name for cb in emc.callbacks] == ["curiosity", "memory"]
    assert emc.algorithm_class is ALGORITHMS["emc"] and type(emc.algorithm) is emc.algorithm_class
    with pytest.raises(KeyError, match="no callback 'nope'; this experiment has"):
        emc.callback("nope")
    emc.close()
    with pytest.raises(ValueError, match="distinct names"):
        Experiment(tiny(), tmp_path / "twice", callbacks=[Recorder(), Recorder()])
    with pytest.raises(
        TypeError, match=r"callbacks\[0\]: the class Recorder, not an instance: pass Recorder\(\)"
    ):
        Experiment(tiny(), tmp_path / "class", callbacks=[Recorder])  # type: ignore[list-item]
    with pytest.raises(
        TypeError, match=r"callbacks\[1\]: expected an mcrs.Callback instance, got builtin_function_or_method"
    ):
        Experiment(tiny(), tmp_path / "function", callbacks=[Recorder(), len])  # type: ignore[list-item]
    assert not (tmp_path / "class").exists() and not (tmp_path / "function").exists()  # refused first


def test_compose_names_overrides_passed_as_one_list() -> None:
    with pytest.raises(TypeError, match=r"compose takes each override as a string .* got a list"):
        compose(["algo=qmix"])  # type: ignore[arg-type]


def test_learner_state_is_the_loss_modules(tmp_path: Path) -> None:
    config = tiny()
    experiment = Experiment(config, tmp_path / "run")
    learner = experiment.learner
    experiment.close()
    with torch.no_grad():  # make the target differ from the online network
        for p in learner.loss.target_agent_network_params.values(True, True):
            p.add_(1.0)
    state = learner.state_dict()
    assert set(state["loss"]) == set(learner.loss.state_dict())
    fresh = Learner(config.algo, config.model, config.train, experiment.env_config, torch.device("cpu"))
    fresh.load_state_dict(state)
    for (name, a), b in zip(learner.loss.state_dict().items(), fresh.loss.state_dict().values(), strict=True):
        assert torch.equal(a, b), name
    for a, b in zip(learner.agent.parameters(), fresh.agent.parameters(), strict=True):
        assert torch.equal(a, b)  # the online agent is the loss's online parameters


@pytest.mark.parametrize(("keep", "expected"), [(2, 2), (0, 4)])
def test_keep_checkpoints_keeps_the_newest_weight_files(tmp_path: Path, keep: int, expected: int) -> None:
    run = tmp_path / "run"
    Experiment(
        tiny("train.total_env_steps=160", "train.checkpoint_interval=40", f"train.keep_checkpoints={keep}"),
        run,
    ).run()
    files = sorted(p.name for p in (run / "checkpoints").glob("model_*.pt"))
    assert len(files) == expected
    assert files[-1] == ckpt.weights_path(run, 160).name  # the newest survives
    assert ckpt.checkpoint_path(run).is_file()
