"""End-to-end training: every algorithm runs, logs, checkpoints, resumes identically and refuses bad input."""

from __future__ import annotations

import csv
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from mcrs.experiment.config import ConfigError
from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.training.trainer import Experiment, TrainingDiverged
from mcrs.train import resume_config, run
from tests.train_helpers import TINY, TINY_MEMORY, compose_config

pytestmark = pytest.mark.slow


def scalars(run_dir: Path, name: str) -> list[tuple[int, float]]:
    with open(run_dir / "logs" / "scalars" / f"{name}.csv") as f:
        return [(int(float(step)), float(value)) for step, value in csv.reader(f)]


@pytest.mark.parametrize("algo", ["qmix", "vdn", "qplex"])
def test_each_algorithm_trains_logs_and_checkpoints(algo: str, tmp_path: Path) -> None:
    cfg = compose_config(f"algo={algo}")
    result = Experiment(cfg, tmp_path).run()
    assert math.isfinite(result["episode_reward"])
    losses = scalars(tmp_path, "train/loss_td")
    assert losses and all(math.isfinite(v) for _, v in losses)
    assert scalars(tmp_path, "train/updates")[-1][1] > 0
    assert [step for step, _ in scalars(tmp_path, "eval/episode_reward")] == [0, 120, 200]
    for metric in ("targets_found", "uncertainty", "collisions", "coverage"):
        assert scalars(tmp_path, f"eval/{metric}")
    assert scalars(tmp_path, "time/env_steps_per_s")[-1][1] > 0
    assert (tmp_path / "config.yaml").is_file()
    state = ckpt.load(ckpt.checkpoint_path(tmp_path))
    assert state["counters"]["env_steps"] == 200 and state["config"]["algo"]["mixer"] == algo
    assert (tmp_path / "checkpoints" / "model_000000200.pt").is_file()


@pytest.mark.parametrize(("per_episode", "expected"), [(0.25, 5), (0.0, 0), (2.0, 40)])
def test_updates_per_collected_episode(per_episode: float, expected: int, tmp_path: Path) -> None:
    # 200 steps of 10-step episodes in batches of 4 envs: 5 batches of 4 episodes, all of them trainable.
    trainer = Experiment(compose_config(f"train.updates_per_episode={per_episode}"), tmp_path)
    trainer.run()
    assert trainer.counters.updates == expected


def test_target_network_is_updated_on_schedule(tmp_path: Path) -> None:
    trainer = Experiment(
        compose_config("train.total_env_steps=40", "train.target_update_episodes=1000"), tmp_path
    )
    learner = trainer.learner
    before = learner.loss.target_agent_network_params["fc1", "weight"].clone()
    trainer.run()
    after_training = learner.loss.target_agent_network_params["fc1", "weight"]
    assert torch.equal(before, after_training)  # no target update within 1000 episodes
    assert not torch.equal(after_training, learner.agent.fc1.weight)  # while the online net learned
    learner.target_updater.step()
    assert torch.equal(learner.loss.target_agent_network_params["fc1", "weight"], learner.agent.fc1.weight)


@pytest.mark.parametrize(("num_envs", "interval", "expected_at"), [
    (4, 6, [8, 12, 20, 24, 32, 36, 44, 48]),  # one copy per multiple of 6 crossed (not every 8)
    (4, 8, [8, 16, 24, 32, 40, 48]),
    (4, 20, [20, 40]),
    (4, 5, [8, 12, 16, 20, 28, 32, 36, 40, 48]),  # 24 and 44 cross no multiple of 5
])  # fmt: skip
def test_target_updates_once_per_interval_whatever_num_envs(
    num_envs: int, interval: int, expected_at: list[int], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # 50 episodes of 10 steps in batches of num_envs: the copies happen at the first batch boundary at or
    # after each multiple of the interval, so their number is floor(episodes / interval), never less.
    trainer = Experiment(
        compose_config(
            "train.total_env_steps=480",
            f"train.num_envs={num_envs}",
            f"train.target_update_episodes={interval}",
        ),
        tmp_path,
    )
    copies: list[int] = []
    monkeypatch.setattr(
        trainer.learner.target_updater, "step", lambda: copies.append(trainer.counters.episodes)
    )
    trainer.run()
    assert copies == expected_at
    assert len(copies) == trainer.counters.episodes // interval


def test_resume_gives_the_same_parameters_as_a_straight_run(tmp_path: Path) -> None:
    straight = Experiment(compose_config("train.total_env_steps=200"), tmp_path / "straight")
    straight.run()
    half = Experiment(compose_config("train.total_env_steps=80"), tmp_path / "half")
    half.run()
    cfg, run_dir = resume_config(compose_config(f"resume={tmp_path / 'half'}", "train.total_env_steps=200"),
                                 [f"resume={tmp_path / 'half'}", "train.total_env_steps=200"])  # fmt: skip
    resumed = Experiment(cfg, run_dir, resume=True)
    assert resumed.counters.env_steps == 80
    resumed.run()
    for name, value in straight.learner.agent.state_dict().items():
        assert torch.equal(value, resumed.learner.agent.state_dict()[name]), name
    for name, value in straight.learner.mixer.state_dict().items():
        assert torch.equal(value, resumed.learner.mixer.state_dict()[name]), name
    assert straight.counters == resumed.counters


def test_resume_refuses_bad_directories_and_contradictions(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no such directory"):
        resume_config(compose_config(f"resume={tmp_path / 'nope'}"), [])
    (tmp_path / "empty").mkdir()
    with pytest.raises(ConfigError, match="not an mcrs-train run directory"):
        resume_config(compose_config(f"resume={tmp_path / 'empty'}"), [])
    Experiment(compose_config("train.total_env_steps=20"), tmp_path / "run").run()
    overrides = [f"resume={tmp_path / 'run'}", "algo=vdn"]
    with pytest.raises(ConfigError, match=r"algo\.mixer: the run has 'qmix', this command has 'vdn'"):
        resume_config(compose_config(*overrides), overrides)
    # A mutable override changes exactly its own field.
    overrides = [f"resume={tmp_path / 'run'}", "logger.log_interval=7", "train.total_env_steps=40"]
    cfg, _ = resume_config(compose_config(*overrides, "logger.progress_bar=true", tiny=False), overrides)
    assert (cfg.logger.log_interval, cfg.logger.progress_bar, cfg.train.total_env_steps) == (7, False, 40)
    # Without explicit overrides the run's own config is used, whatever the defaults say.
    cfg, _ = resume_config(
        compose_config(f"resume={tmp_path / 'run'}", tiny=False), [f"resume={tmp_path / 'run'}"]
    )
    assert cfg.env.max_steps == 10 and cfg.train.num_envs == 4


def test_corrupt_and_foreign_checkpoints_are_refused(tmp_path: Path) -> None:
    Experiment(compose_config("train.total_env_steps=20"), tmp_path / "run").run()
    good = ckpt.checkpoint_path(tmp_path / "run")
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(good.read_bytes()[:1000])
    with pytest.raises(ckpt.CheckpointError, match="cannot be read safely"):
        ckpt.load(truncated)
    foreign = tmp_path / "foreign.pt"
    torch.save({"weights": torch.zeros(3)}, foreign)
    with pytest.raises(ckpt.CheckpointError, match="not an mcrs checkpoint"):
        ckpt.load(foreign)

    class Evil:
        def __reduce__(self):
            return (os.system, ("echo pwned",))

    pickled = tmp_path / "evil.pt"
    torch.save({"format": ckpt.FORMAT, "x": Evil()}, pickled)
    with pytest.raises(ckpt.CheckpointError, match="cannot be read safely"):
        ckpt.load(pickled)


def test_non_finite_loss_stops_the_run_and_keeps_the_last_good_state(tmp_path: Path) -> None:
    cfg = compose_config("env.w_uncertainty=1e37")  # finite rewards whose squared TD errors overflow
    trainer = Experiment(cfg, tmp_path)
    with pytest.raises(TrainingDiverged, match=r"non-finite loss_td=.* at env step \d+ \(update 1\)"):
        trainer.run()
    state = ckpt.load(tmp_path / "checkpoints" / "last_good.pt")
    assert state["counters"]["updates"] == 0


def test_non_finite_memory_term_is_named(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    trainer = Experiment(compose_config("algo=cnn_semu", *TINY_MEMORY), tmp_path)
    forward = trainer.learner.loss.forward

    def broken_memory_term(batch):
        out = forward(batch)
        out["loss_memory"] = torch.tensor(float("nan"))
        out["loss"] = out["loss"] + out["loss_memory"]
        return out

    monkeypatch.setattr(trainer.learner.loss, "forward", broken_memory_term)
    with pytest.raises(TrainingDiverged, match=r"non-finite loss_memory=nan at env step \d+ \(update 1\)"):
        trainer.run()
    assert ckpt.load(tmp_path / "checkpoints" / "last_good.pt")["counters"]["updates"] == 0


@pytest.mark.parametrize(
    ("key", "term"),
    [
        ("state", "belief maps / state"),
        (("next", "reward"), "reward"),
        (("agents", "observation"), "observation"),
    ],
)
def test_non_finite_env_output_stops_before_the_replay(
    key, term: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    trainer = Experiment(compose_config("train.total_env_steps=80"), tmp_path)
    next_batch = trainer.collector.next_batch
    calls = []

    def poisoned(iterator):
        batch = next_batch(iterator)
        calls.append(1)
        if len(calls) == 2:  # the second batch carries a NaN belief / reward / observation
            batch.get(key).view(-1)[3] = float("nan")
        return batch

    monkeypatch.setattr(trainer.collector, "next_batch", poisoned)
    with pytest.raises(
        TrainingDiverged, match=rf"non-finite {re.escape(term)} in the episodes collected after env step 40"
    ):
        trainer.run()
    state = ckpt.load(tmp_path / "checkpoints" / "last_good.pt")
    assert state["counters"]["env_steps"] == 40 and state["replay"]["length"] == 4  # only the good batch


@pytest.mark.parametrize("logger", ["wandb", "tensorboard"])
def test_other_loggers_write_locally(logger: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("WANDB_MODE", "offline")
    Experiment(compose_config(f"logger={logger}", "train.total_env_steps=20"), tmp_path).run()
    if logger == "wandb":
        assert list((tmp_path / "wandb").glob("offline-run-*"))
    else:
        assert list((tmp_path / "logs").rglob("events.out.tfevents.*"))


def test_run_prints_and_returns_the_final_evaluation(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    result = run(compose_config("train.total_env_steps=20"), tmp_path)
    assert "episode_reward" in result
    assert f"run directory: {tmp_path}" in capsys.readouterr().out


def cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "HYDRA_FULL_ERROR": "0"}
    return subprocess.run(
        [sys.executable, "-m", "mcrs.train", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_cli_trains_from_any_directory_and_sweeps(tmp_path: Path) -> None:
    done = cli("-m", *TINY, "train.total_env_steps=40", "algo=qmix,vdn", "seed=0,1", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    runs = sorted(
        p.name
        for p in (tmp_path / "outputs" / "multirun").glob("*/*")
        if p.is_dir() and not p.name.startswith(".")
    )  # .sweep: the sweep summary's rows
    assert runs == ["0_map10_qmix_seed0", "1_map10_qmix_seed1", "2_map10_vdn_seed0", "3_map10_vdn_seed1"]
    for log in (tmp_path / "outputs" / "multirun").glob("*/*/train.log"):  # the run's own log, plain text
        text = log.read_text()
        assert "evaluation at env step 0: episode_reward" in text and "checkpoint at env step" in text, text
        assert "\x1b" not in text
    assert len(list((tmp_path / "outputs" / "multirun").glob("*/*/train.log"))) == 4
    assert "LazyTensorStorage" not in done.stdout + done.stderr  # TorchRL's INFO line stays quiet


def test_cli_joblib_launcher(tmp_path: Path) -> None:
    done = cli("-m", *TINY, "train.total_env_steps=40", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2",
               "seed=0,1", cwd=tmp_path)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert len(list((tmp_path / "outputs" / "multirun").glob("*/*/checkpoints/last.pt"))) == 2


def test_cli_bad_input_is_one_clear_message(tmp_path: Path) -> None:
    done = cli(*TINY, "train.lr=-1", "model.hidden_dim=0", cwd=tmp_path)
    assert done.returncode != 0
    assert "mcrs-train: error: invalid config" in done.stderr
    assert "train.lr=-1.0: must be > 0" in done.stderr and "model.hidden_dim=0: must be > 0" in done.stderr
    assert "Traceback" not in done.stderr
    done = cli(*TINY, "algo.mixer=qtran", cwd=tmp_path)  # a choice: Hydra refuses it while composing
    assert done.returncode != 0 and "Traceback" not in done.stderr
    assert done.stderr == "mcrs-train: error: algo.mixer=qtran: allowed values: qmix, vdn, qplex\n", (
        done.stderr
    )
    done = cli(f"resume={tmp_path / 'missing'}", cwd=tmp_path)
    assert done.returncode != 0 and "no such directory" in done.stderr


def test_resume_may_switch_the_collector(tmp_path: Path) -> None:
    """A multiprocess run whose worker crashed may go on in one process (train.collector* are mutable)."""
    Experiment(compose_config("train.total_env_steps=40"), tmp_path / "run").run()
    args = [f"resume={tmp_path / 'run'}", "train.collector=multiprocess", "train.collector_workers=4"]
    cfg, _ = resume_config(compose_config(*args), args)
    assert cfg.train.collector == "multiprocess" and cfg.train.collector_workers == 4


def test_a_resume_to_a_length_the_run_has_passed_says_there_is_nothing_to_train(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    from mcrs.train import run

    Experiment(compose_config("train.total_env_steps=80"), tmp_path / "run").run()
    overrides = [f"resume={tmp_path / 'run'}", "train.total_env_steps=40"]
    run(compose_config(*overrides), tmp_path / "run", overrides)
    assert (
        "note: the run is already at 80 env steps (train.total_env_steps=40): nothing to train"
        in capsys.readouterr().out
    )
