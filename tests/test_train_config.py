"""The training config: every group composes, typos and wrong types fail at start, bad values are named."""

from __future__ import annotations

import itertools

import pytest
import torch
from hydra.errors import ConfigCompositionException
from omegaconf.errors import ConfigKeyError, ValidationError

from mcrs.experiment.config import ConfigError, as_typed, validate, validation_errors
from mcrs.experiment.training.learner import Learner
from tests.train_helpers import compose_config

ENVS, ALGOS, LOGGERS, PRESETS = (
    ("map10", "map15", "map20"),
    ("qmix", "vdn", "qplex"),
    ("csv", "wandb", "tensorboard"),
    ("pymarl", "pymarl2"),
)


COMBINATIONS = [
    *((env, algo, "csv", "pymarl") for env, algo in itertools.product(ENVS, ALGOS)),
    *(("map10", "qmix", logger, preset) for logger, preset in itertools.product(LOGGERS, PRESETS)),
]


@pytest.mark.parametrize(("env", "algo", "logger", "preset"), COMBINATIONS)
def test_every_group_combination_composes_and_validates(
    env: str, algo: str, logger: str, preset: str
) -> None:
    cfg = compose_config(f"env={env}", f"algo={algo}", f"logger={logger}", f"preset={preset}", tiny=False)
    assert validation_errors(cfg) == []
    assert (cfg.env.name, cfg.algo.mixer, cfg.logger.backend, cfg.preset) == (env, algo, logger, preset)


def test_defaults_are_the_paper_setting() -> None:
    cfg = compose_config(tiny=False)
    assert (cfg.env.name, cfg.algo.name, cfg.preset, cfg.logger.backend) == ("map10", "qmix", "pymarl", "csv")
    t = cfg.train
    assert (t.batch_episodes, t.replay_episodes, t.optimizer, t.lr, t.eps_anneal_steps) == (
        32,
        5000,
        "rmsprop",
        5e-4,
        50_000,
    )
    assert (t.target_update_episodes, t.eval_interval, t.eval_episodes, t.total_env_steps) == (
        200,
        10_000,
        32,
        2_000_000,
    )
    assert (cfg.algo.gamma, cfg.algo.td_lambda, cfg.algo.hypernet_layers) == (0.99, 0.0, 2)
    assert cfg.logger.wandb_mode == "offline"


def test_pymarl2_preset() -> None:
    cfg = compose_config("preset=pymarl2", tiny=False)
    assert (
        cfg.train.optimizer,
        cfg.train.lr,
        cfg.algo.td_lambda,
        cfg.train.batch_episodes,
        cfg.train.num_envs,
    ) == ("adam", 1e-3, 0.6, 128, 8)
    cfg = compose_config("preset=pymarl2", "train.lr=0.01", tiny=False)  # the command line wins
    assert cfg.train.lr == 0.01


@pytest.mark.parametrize(
    "override", ["algo.lrr=1", "train.batch=3", "loger.backend=csv", "model.hiden_dim=3"]
)
def test_unknown_keys_fail_at_compose(override: str) -> None:
    with pytest.raises((ConfigCompositionException, ConfigKeyError)):
        compose_config(override)


@pytest.mark.parametrize(
    "override", ["train.lr=abc", "train.batch_episodes=1.5", "algo.double_q=maybe", "seed=x"]
)
def test_wrong_types_fail_at_compose(override: str) -> None:
    with pytest.raises((ConfigCompositionException, ValidationError)):
        compose_config(override)


@pytest.mark.parametrize("group", ["algo=foo", "logger=mlflow", "preset=pymarl3", "env=map30"])
def test_unknown_group_options_list_the_allowed_ones(group: str) -> None:
    with pytest.raises(ConfigCompositionException) as info:
        compose_config(group)
    message = str(info.value) + str(info.value.__cause__)
    assert "Available options" in message


@pytest.mark.parametrize(
    ("override", "expected"),
    [
        ("algo.gamma=1.5", "algo.gamma=1.5: must be in [0, 1]"),
        ("algo.td_lambda=-0.1", "algo.td_lambda=-0.1: must be in [0, 1]"),
        ("algo.hypernet_layers=3", "algo.hypernet_layers=3: allowed values are 1, 2"),
        ("train.batch_episodes=0", "train.batch_episodes=0: must be > 0"),
        ("train.lr=-1", "train.lr=-1.0: must be > 0"),
        ("train.eval_interval=0", "train.eval_interval=0: must be > 0"),
        ("train.updates_per_episode=-1", "train.updates_per_episode=-1.0: must be >= 0"),
        ("train.eps_start=1.5", "train.eps_start=1.5: must be in [0, 1]"),
        ("train.eps_start=0.01", "train.eps_end=0.05 > train.eps_start=0.01"),
        ("train.replay_episodes=2", "train.replay_episodes=2 < train.batch_episodes=4"),
        ("model.hidden_dim=0", "model.hidden_dim=0: must be > 0"),
        ("device=cuda:7", "device='cuda:7'"),
        ("device=tpu", "device='tpu'"),
        ("env.n_uavs=0", "env.n_uavs=0: must be an integer >= 1"),
        ("env.comm_range=-1", "comm_range"),
    ],
)
def test_bad_values_are_named(override: str, expected: str) -> None:
    cfg = compose_config(override)
    errors = validation_errors(cfg)
    assert any(expected in e for e in errors), errors
    with pytest.raises(ConfigError, match="invalid config"):
        validate(cfg)


def test_all_problems_are_reported_at_once() -> None:
    cfg = compose_config("train.lr=-1", "train.eps_start=2", "model.hidden_dim=0")
    assert len(validation_errors(cfg)) == 3


def test_a_python_built_config_of_wrong_types_is_refused_field_by_field() -> None:
    """OmegaConf never sees a Config built in Python: validate names every mistyped field in full."""
    from mcrs.experiment.config import AlgoConfig, Config, MemoryConfig, TrainConfig

    cfg = Config(
        seed="3",
        train=TrainConfig(lr="abc", total_env_steps=True),
        algo=AlgoConfig(gamma=None, memory=MemoryConfig(delta="a")),
    )
    with pytest.raises(ConfigError) as info:
        validate(cfg)
    message = str(info.value)
    for expected in (
        "seed='3': must be of type int (got str)",
        "train.lr='abc': must be of type float (got str)",
        "train.total_env_steps=True: must be of type int (got bool)",
        "algo.gamma=None: must be of type float (got NoneType)",
        "algo.memory.delta='a': must be of type float (got str)",
    ):
        assert expected in message, message
    # what the schema admits passes: an int where a float is wanted, None where None is allowed, a count
    # of threads (its own check), a choice by its name
    admitted = Config(train=TrainConfig(lr=1), resume=None, threads=2, algo=AlgoConfig(mixer="vdn"))
    assert validation_errors(admitted, deep=False) == []


def test_launcher_configs_compose() -> None:
    import importlib.util

    from hydra import compose, initialize_config_dir
    from hydra.errors import MissingConfigException

    from mcrs.train import CONFIG_DIR

    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        slurm = compose(config_name="config", overrides=["hydra/launcher=slurm"], return_hydra_config=True)
        assert slurm.hydra.launcher._target_.endswith("SlurmLauncher")
        assert slurm.hydra.launcher.cpus_per_task == 2
        joblib = compose(config_name="config", overrides=["hydra/launcher=joblib"], return_hydra_config=True)
        assert joblib.hydra.launcher._target_.endswith("JoblibLauncher")
        if importlib.util.find_spec("hydra_plugins.hydra_ray_launcher") is None:
            # Without `pip install mcrs[ray]` the config names the missing plugin config.
            with pytest.raises(MissingConfigException, match="hydra/launcher/ray"):
                compose(
                    config_name="config", overrides=["hydra/launcher=ray_cluster"], return_hydra_config=True
                )
        else:
            ray = compose(
                config_name="config", overrides=["hydra/launcher=ray_cluster"], return_hydra_config=True
            )
            assert ray.hydra.launcher.ray.remote.num_cpus == 2


@pytest.mark.parametrize("budget", ["quickstart", "paper", "cpu"])
def test_foreground_budgets_show_progress_and_paper_writes_the_report_as_quickstart(budget: str) -> None:
    """A budget run in the foreground shows its progress (the bar, or plain lines where the console is a
    log file); the paper's 2M-step run ends with the same report/ as the quickstart."""
    cfg = compose_config(f"budget={budget}", tiny=False)
    assert cfg.logger.progress_bar is True
    assert cfg.report is (budget in ("quickstart", "paper"))


def test_the_campaigns_background_children_keep_the_bar_off(tmp_path) -> None:
    from mcrs_lab.campaign.matrix import Point

    assert compose_config("budget=campaign", tiny=False).logger.progress_bar is False
    assert compose_config("budget=smoke", tiny=False).logger.progress_bar is False  # seconds a point
    point = Point("baselines", "map20", "qmix", 0, "campaign")
    assert "budget=campaign" in point.train_command(tmp_path)  # a fresh child: the budget's bar, off
    assert "logger.progress_bar=false" in point.resume_command(tmp_path, 1000)


def test_a_budget_off_whole_batches_from_a_preset_or_python_is_said_not_rounded_silently() -> None:
    from mcrs.experiment.training.whole_batches import rounding_notes

    assert rounding_notes(3200, 1_000_000, 9600) == [
        "train.total_env_steps=1000000 is not a whole number of collector batches of 3200 env steps: "
        "the run trains 1,001,600 env steps"
    ]
    assert rounding_notes(40, 50, 60) == [
        "train.total_env_steps=50 is not a whole number of collector batches of 40 env steps: "
        "the run trains 80 env steps",
        "train.eval_interval=60 is not a whole number of collector batches of 40 env steps: "
        "the run evaluates at the first batch end at or after each multiple of it: env steps 80, 120, 200, ...",
    ]
    assert rounding_notes(40, 200, 120) == []  # whole batches: nothing to say


def test_the_experiment_logs_the_rounding_of_a_python_built_budget(tmp_path, caplog) -> None:
    import logging

    from mcrs.experiment.config import compose
    from mcrs.experiment.training.trainer import Experiment
    from tests.train_helpers import TINY

    with caplog.at_level(logging.INFO, logger="mcrs.run"):
        Experiment(compose("algo=qmix", *TINY, "train.total_env_steps=50"), tmp_path / "run").close()
    assert (
        "train.total_env_steps=50 is not a whole number of collector batches of 40 env steps: the run "
        "trains 80 env steps" in caplog.text
    )


def test_the_evaluation_note_says_the_steps_the_run_evaluates_at(tmp_path, caplog) -> None:
    import logging
    import re

    from mcrs.experiment.config import compose
    from mcrs.experiment.run.logging import read_scalar_rows, scalar_file
    from mcrs.experiment.training.trainer import Experiment
    from tests.train_helpers import TINY

    config = compose("algo=qmix", *TINY, "train.total_env_steps=200", "train.eval_interval=60")
    with caplog.at_level(logging.INFO, logger="mcrs.run"):
        Experiment(config, tmp_path / "run").run()
    said = re.search(r"train.eval_interval=60 .* env steps ([\d, ]+), \.\.\.", caplog.text)
    assert said is not None, caplog.text
    steps = [int(s) for s, _ in read_scalar_rows(scalar_file(tmp_path / "run", "eval/episode_reward"))]
    assert steps[1:4] == [int(s) for s in said.group(1).split(", ")]  # after the one at step 0


def test_a_run_that_never_updates_says_so(tmp_path, caplog) -> None:
    import logging

    from mcrs.experiment.config import compose
    from mcrs.experiment.training.trainer import Experiment
    from tests.train_helpers import TINY

    with caplog.at_level(logging.INFO, logger="mcrs.run"):
        Experiment(compose("algo=qmix", *TINY, "train.updates_per_episode=0"), tmp_path / "run").close()
    assert "train.updates_per_episode=0: the run collects and evaluates but never updates" in caplog.text


@pytest.mark.parametrize("algo", ["qmix", "emu"])
def test_reward_scale_reaches_the_learners_loss(algo: str) -> None:
    cfg = as_typed(compose_config(f"algo={algo}", "algo.reward_scale=0.05"))
    learner = Learner(cfg.algo, cfg.model, cfg.train, validate(cfg), torch.device("cpu"))
    assert learner.loss.reward_scale == 0.05
    if algo == "emu":  # the threshold is compared with the env's returns: not scaled
        assert learner.loss.incentive.threshold == 365.0


def test_a_misspelt_field_set_in_python_is_an_error_naming_the_closest() -> None:
    import mcrs

    config = mcrs.compose("algo=qmix")
    config.train.total_env_steps = 3200  # a field: set
    assert config.train.total_env_steps == 3200
    for node, name, closest in (
        (config.train, "total_env_step", "total_env_steps"),
        (config.env, "comm_rage", "comm_range"),
        (config.algo.memory, "dleta", "delta"),
        (config, "sed", "seed"),
    ):
        with pytest.raises(AttributeError, match=rf"has no field '{name}' \(closest: {closest}"):
            setattr(node, name, 1)
        assert not hasattr(node, name)
