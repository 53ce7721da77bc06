"""The task interface (mcrs.experiment.training.task): ``Experiment(config, run_dir, task=...)`` trains and evaluates a
task we did not write (the matrix game) through the same loop, checkpoints and logs as MCRS, MCRS through an
explicit :class:`MCRSTask` is the default run, and what a task cannot run is refused in one line."""

from __future__ import annotations

import csv
import pickle
from pathlib import Path

import pytest
import torch

from mcrs.experiment.config import ConfigError, compose, validate
from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.training.task import MCRSTask
from mcrs.experiment.training.trainer import Experiment
from mcrs.tasks import MatrixGameEnv, MatrixGameTask
from tests.train_helpers import TINY

#: A game whose optimum (0, 0) a monotonic mixer can represent: QMIX trained on uniformly random joint
#: actions must find it, and the untrained greedy agents (seed 0) do not play it.
EASY = torch.tensor([[5.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])

#: The matrix game's run: 32 games per batch (each one whole 1-step episode), uniform exploration (the game's
#: standard protocol), Adam; 640 episodes, evaluated every 320.
GAME = [
    "algo=qmix",
    "threads=1",
    "logger.progress_bar=false",
    "train.total_env_steps=640",
    "train.num_envs=32",
    "train.batch_episodes=64",
    "train.replay_episodes=1024",
    "train.eval_interval=320",
    "train.eval_episodes=1",
    "train.checkpoint_interval=640",
    "train.eps_start=1",
    "train.eps_end=1",
    "train.optimizer=adam",
    "train.lr=0.005",
    "train.updates_per_episode=0.125",
    "train.target_update_episodes=64",
    "model.hidden_dim=16",
]


def _eval_rewards(run_dir: Path) -> list[tuple[int, float]]:
    with (run_dir / "logs" / "scalars" / "eval" / "episode_reward.csv").open() as f:
        return [(int(row[0]), float(row[1])) for row in csv.reader(f)]


def test_the_matrix_game_trains_through_the_experiment_and_learns(tmp_path: Path) -> None:
    """QMIX on a task we did not write, through Experiment: logs, checkpoints, and the greedy agents learn
    the optimal joint action (payoff 5) that the untrained ones do not play."""
    task = MatrixGameTask(EASY)
    experiment = Experiment(compose(*GAME), tmp_path, task=task)
    final = experiment.run()
    rewards = _eval_rewards(tmp_path)  # greedy evaluations at env steps 0 (untrained), 320 and 640
    assert [step for step, _ in rewards] == [0, 320, 640]
    assert rewards[0][1] < 5.0
    assert rewards[-1][1] == final["episode_reward"] == 5.0
    state = torch.load(ckpt.checkpoint_path(tmp_path), weights_only=False)
    assert state["fingerprint"]["task.name"] == "matrix_game"
    assert state["counters"]["env_steps"] == 640 and state["counters"]["updates"] == 76  # from the 2nd batch


def test_explicit_mcrs_task_is_the_default_run(tmp_path: Path) -> None:
    """``task=MCRSTask(env_config)`` is the run without ``task``: the same evaluation CSVs, byte for byte."""
    config = compose("algo=qmix", *TINY, "train.total_env_steps=80", "train.eval_interval=40")
    Experiment(config, tmp_path / "default").run()
    Experiment(config, tmp_path / "explicit", task=MCRSTask(validate(config))).run()
    evals = sorted((tmp_path / "default" / "logs" / "scalars" / "eval").glob("*.csv"))
    assert evals
    for path in evals:
        other = tmp_path / "explicit" / "logs" / "scalars" / "eval" / path.name
        assert path.read_bytes() == other.read_bytes(), path.name


def test_a_resume_on_another_task_is_refused_in_one_line(tmp_path: Path) -> None:
    config = compose(
        *GAME, "train.total_env_steps=64", "train.eval_interval=64", "train.checkpoint_interval=64"
    )
    Experiment(config, tmp_path, task=MatrixGameTask()).run()
    with pytest.raises(ckpt.CheckpointError) as error:
        Experiment(config, tmp_path, resume=True)  # MCRS on config.env
    assert "does not belong to this run" in str(error.value) and "task." in str(error.value)
    assert "\n" not in str(error.value)
    with pytest.raises(ckpt.CheckpointError, match=r"task\.payoff"):  # another payoff: another task
        Experiment(config, tmp_path, resume=True, task=MatrixGameTask(EASY))
    resumed = Experiment(config, tmp_path, resume=True, task=MatrixGameTask())  # the same task resumes
    assert resumed.counters.env_steps == 64
    resumed.close()


@pytest.mark.parametrize(
    ("overrides", "field"),
    [
        (["algo=cnn_semu"], "algo.memory.enabled"),
        (["logger.video=true"], "logger.video"),
        (["algo.curiosity_scale=0.1"], "algo.curiosity_scale"),
    ],
)
def test_what_the_matrix_game_cannot_run_is_refused(tmp_path: Path, overrides: list[str], field: str) -> None:
    with pytest.raises(ConfigError) as error:
        Experiment(compose(*GAME, *overrides), tmp_path, task=MatrixGameTask())
    assert field in str(error.value)
    assert "Traceback" not in str(error.value)


class _Unpicklable(MatrixGameTask):
    def __init__(self) -> None:
        super().__init__()
        self.hook = lambda: None  # a lambda: not picklable


def test_multiprocess_needs_a_picklable_task(tmp_path: Path) -> None:
    config = compose(*GAME, "train.collector=multiprocess", "train.collector_workers=2")
    with pytest.raises(ConfigError, match=r"train\.collector=multiprocess.*cannot be pickled"):
        Experiment(config, tmp_path, task=_Unpicklable())
    pickle.dumps(MatrixGameTask())  # the matrix game itself is picklable: its workers can build it


def test_the_task_describes_its_env() -> None:
    task = MatrixGameTask()
    env = task.make_env(4, torch.device("cpu"))
    assert isinstance(env, MatrixGameEnv) and env.batch_size == (4,)
    assert env.observation_spec[task.observation_key].shape == (4, task.n_agents, task.obs_dim)
    assert env.observation_spec[task.state_key].shape == (4, *task.state_shape)
    assert env.action_spec[task.action_key].space.n == task.n_actions


class _WrongSizes(MatrixGameTask):
    """Declares sizes its env does not have: the networks would be built to them."""

    def __init__(self) -> None:
        super().__init__()
        self.n_actions, self.obs_dim = 4, 5


class _WrongState(MatrixGameTask):
    def __init__(self) -> None:
        super().__init__()
        self.state_key = "state"


@pytest.mark.parametrize(
    ("task", "expected"),
    [
        (_WrongSizes(), r"n_agents, obs_dim = \(2, 5\), but its env's \('players', 'observation'\) is \(2, 2\) per env; "
         r"n_agents, n_actions = \(2, 4\), but its env's \('players', 'action_mask'\) is \(2, 3\)"),
        (_WrongState(), r"its env has no observation key 'state'"),
    ],
)  # fmt: skip
def test_a_task_whose_env_disagrees_with_its_sizes_is_refused_naming_them(
    task: MatrixGameTask, expected: str, tmp_path: Path
) -> None:
    with pytest.raises(ConfigError, match=rf"^task 'matrix_game' \({type(task).__name__}\): .*{expected}"):
        Experiment(compose(*GAME), tmp_path, task=task)
