"""End-to-end training with the episodic memory: every memory algorithm runs, logs its diagnostics,
checkpoints its memory, resumes identically, and refuses bad memory settings."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from mcrs.experiment.config import ConfigError, validate
from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.training.episodic import EpisodicMemoryCallback
from mcrs.experiment.training.trainer import Experiment
from mcrs.train import CONFIG_DIR, resume_config
from tests.device_helpers import available_devices
from tests.train_helpers import TINY_MEMORY, compose_config

pytestmark = pytest.mark.slow

MEMORY_ALGOS = ["emc", "emu", "emu_370", "emu_change", "semu", "cnn_semu"]


def scalars(run_dir: Path, name: str) -> list[tuple[int, float]]:
    with open(run_dir / "logs" / "scalars" / f"{name}.csv") as f:
        return [(int(float(step)), float(value)) for step, value in csv.reader(f)]


def memory_config(*overrides: str):
    return compose_config(*TINY_MEMORY, *overrides)


def test_mcrs_train_defaults_to_cnn_semu() -> None:
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose(config_name="config")
    assert cfg.algo.name == "cnn_semu" and cfg.env.name == "map10"
    assert cfg.algo.memory.enabled and cfg.algo.memory.embedding == "cnn" and cfg.algo.memory_weight == 0.1
    assert cfg.algo.memory.capacity == 1_000_000 and cfg.algo.memory.delta == pytest.approx(1.3e-3)


@pytest.mark.parametrize("algo", MEMORY_ALGOS)
def test_each_memory_algorithm_trains_and_logs_its_diagnostics(algo: str, tmp_path: Path) -> None:
    cfg = memory_config(f"algo={algo}")
    trainer = Experiment(cfg, tmp_path)
    result = trainer.run()
    assert math.isfinite(result["episode_reward"])
    # 200 env steps of 10-step episodes: 20 x 11 states s_0..s_10 inserted (hits update instead of adding).
    size = scalars(tmp_path, "memory/size")
    assert size and 0 < size[-1][1] <= 220 and len(trainer.callback("memory").memory) == size[-1][1]
    names = ("train/memory_hit_rate", "train/q_taken_mean", "memory/insert_new", "memory/insert_hit_rate",
             "memory/lookup_hit_rate", "memory/foreign_hit_rate", "memory/tolerance")  # fmt: skip
    for name in names:
        assert scalars(tmp_path, name), name
    assert all(0 <= v <= 1 for _, v in scalars(tmp_path, "memory/foreign_hit_rate"))
    if cfg.algo.memory.embedding != "random":  # phi trained at 80 and 160 env steps
        losses = scalars(tmp_path, "memory/embedding_loss")
        assert [step for step, _ in losses] and all(math.isfinite(v) for _, v in losses)
    if cfg.algo.memory_weight > 0:
        assert all(math.isfinite(v) for _, v in scalars(tmp_path, "train/loss_memory"))
    if cfg.algo.incentive != "none":
        assert scalars(tmp_path, "train/incentive_mean")
    if cfg.algo.curiosity_scale > 0:
        assert all(v > 0 for _, v in scalars(tmp_path, "train/curiosity_scale"))
    # The checkpoint carries the memory: a fresh memory loaded from it answers look-ups identically.
    state = ckpt.load(ckpt.checkpoint_path(tmp_path))
    fresh = EpisodicMemoryCallback(cfg, trainer.env_config, torch.device("cpu"))
    fresh.load_state_dict(state["callbacks"]["memory"])
    assert len(fresh.memory) == len(trainer.callback("memory").memory)
    states = trainer.replay.storage.get(torch.arange(4)).get("state")[:, 1:]
    time = torch.arange(1, states.shape[1] + 1).float().div(cfg.env.max_steps).expand(4, -1)
    for a, b in zip(
        fresh.memory.lookup(states, time), trainer.callback("memory").memory.lookup(states, time), strict=True
    ):
        assert torch.equal(a, b)


@pytest.mark.parametrize("mixer", ["vdn", "qplex"])
def test_cnn_semu_on_other_mixers(mixer: str, tmp_path: Path) -> None:
    trainer = Experiment(
        memory_config("algo=cnn_semu", f"algo.mixer={mixer}", "train.total_env_steps=80"), tmp_path
    )
    assert math.isfinite(trainer.run()["episode_reward"])


def test_memory_hits_reach_the_loss(tmp_path: Path) -> None:
    """With a huge tolerance every look-up hits: the memory term is active and logged as such."""
    overrides = ("algo.memory.delta=1e6", "algo.memory.delta_rule=literal", "train.total_env_steps=80")
    trainer = Experiment(memory_config("algo=cnn_semu", *overrides), tmp_path)
    trainer.run()
    assert scalars(tmp_path, "train/memory_hit_rate")[-1][1] == pytest.approx(1.0)
    assert scalars(tmp_path, "train/loss_memory")[-1][1] > 0
    # Every transition found an entry: the memory holds one entry per distinct time step at most.
    assert len(trainer.callback("memory").memory) < 80


def _same(a: torch.Tensor, b: torch.Tensor, device: str) -> bool:
    """Bitwise for runs on the CPU. For runs on CUDA, floats to rounding: cuDNN's convolution backward (the
    CNN embedding, and so the memory's keys) is not bitwise reproducible there (docs/TRAINING.md, "On a
    GPU")."""
    if device == "cpu" or not a.is_floating_point():
        return torch.equal(a, b)
    return torch.allclose(a, b, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("device", available_devices())
@pytest.mark.parametrize("algo", ["cnn_semu", "emc"])
def test_resume_continues_with_the_same_memory(algo: str, device: str, tmp_path: Path) -> None:
    overrides = [f"algo={algo}", "train.total_env_steps=200", f"device={device}"]
    straight = Experiment(memory_config(*overrides), tmp_path / "straight")
    straight.run()
    Experiment(
        memory_config(f"algo={algo}", "train.total_env_steps=120", f"device={device}"), tmp_path / "half"
    ).run()
    args = [f"resume={tmp_path / 'half'}", "train.total_env_steps=200"]
    cfg, run_dir = resume_config(memory_config(*args), args)
    resumed = Experiment(cfg, run_dir, resume=True)
    assert len(resumed.callback("memory").memory) > 0
    resumed.run()
    for name, value in straight.learner.agent.state_dict().items():
        assert value.device.type == device and _same(
            value, resumed.learner.agent.state_dict()[name], device
        ), name
    for name, value in straight.callback("memory").embedding.state_dict().items():
        assert _same(value, resumed.callback("memory").embedding.state_dict()[name], device), name
    a, b = straight.callback("memory").memory.state_dict(), resumed.callback("memory").memory.state_dict()
    assert a.keys() == b.keys()
    for key in a:
        if isinstance(a[key], torch.Tensor):
            assert _same(a[key], b[key], device), key
        else:
            assert a[key] == b[key], key
    assert straight.counters == resumed.counters


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("algo.memory.delta=0", r"algo\.memory\.delta=0\.0: must be > 0"),
        ("algo.memory.delta=-1", r"algo\.memory\.delta=-1\.0: must be > 0"),
        ("algo.memory.capacity=0", r"algo\.memory\.capacity=0: must be >= 1 entry"),
        ("algo.memory_weight=-0.1", r"algo\.memory_weight=-0\.1: must be >= 0"),
        ("algo.memory.enabled=false", r"need the episodic memory: set algo\.memory\.enabled=true"),
        ("algo.memory.cnn_channels=[4,4]", r"algo\.memory\.cnn_channels=\[4, 4\]: must be 3 positive"),
        ("algo.curiosity_decay_rate=2", r"algo\.curiosity_decay_rate=2\.0: must be in \[0, 1\]"),
        ("algo.memory.embedding_grad_clip=0", r"algo\.memory\.embedding_grad_clip=0\.0: must be > 0"),
    ],
)
def test_bad_memory_settings_are_refused_at_start(override: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        validate(memory_config("algo=cnn_semu", override))


def test_a_memory_from_another_map_is_refused(tmp_path: Path) -> None:
    small = Experiment(memory_config("algo=cnn_semu", "train.total_env_steps=40"), tmp_path / "a")
    small.run()
    other = Experiment(memory_config("algo=cnn_semu", "env=map15", "env.max_steps=10", "train.total_env_steps=40"),
                    tmp_path / "b")  # fmt: skip
    with pytest.raises(ValueError, match="map"):
        other.callback("memory").memory.load_state_dict(small.callback("memory").memory.state_dict())


def test_curiosity_networks_use_the_learners_optimizer_setting(tmp_path: Path) -> None:
    trainer = Experiment(memory_config("algo=emc", "train.optimizer=adam", "train.lr=0.002"), tmp_path)
    curiosity = trainer.callback("curiosity").curiosity
    for optimizer in (curiosity.vdn_optimizer, curiosity.predictor_optimizer, trainer.learner.optimizer):
        assert isinstance(optimizer, torch.optim.Adam) and optimizer.defaults["lr"] == 0.002
