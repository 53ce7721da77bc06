"""A trained checkpoint as a policy: mcrs-eval and mcrs-render run it like a heuristic."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from mcrs.env import MCRSEnv, scenario
from mcrs.evaluate import evaluate_episodes, evaluate_policy
from mcrs.experiment.training.trainer import Experiment
from mcrs.models.acting import recurrent_primer
from mcrs.policies import check_policy, make_policy
from mcrs.policies.trained import TrainedPolicy
from mcrs.viz import write_episode_pictures
from tests.train_helpers import compose_config


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("run")
    Experiment(compose_config("train.total_env_steps=80"), path).run()
    return path


@pytest.mark.slow
def test_checkpoint_policy_matches_the_training_greedy_policy(run_dir: Path) -> None:
    trainer = Experiment(compose_config("train.total_env_steps=80"), run_dir, resume=True)
    env_config = scenario("map10", max_steps=10, num_envs=3)
    policy = make_policy(str(run_dir), env_config)
    assert isinstance(policy, TrainedPolicy)
    env = MCRSEnv(env_config)
    env.set_seed(5)
    ours = env.rollout(10, policy, break_when_any_done=False)
    from torchrl.envs import TransformedEnv
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    primed = TransformedEnv(MCRSEnv(env_config), recurrent_primer(3, env_config.n_uavs, 16))
    primed.set_seed(5)
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        reference = primed.rollout(10, trainer.greedy, break_when_any_done=False)
    assert torch.equal(ours["agents", "action"], reference["agents", "action"])


def test_eval_and_render_accept_checkpoints(run_dir: Path, tmp_path: Path) -> None:
    env_config = scenario("map10", max_steps=10)
    model = sorted((run_dir / "checkpoints").glob("model_*.pt"))[-1]
    result = evaluate_policy(env_config, str(model), episodes=3, seed=0)
    assert result["episode_reward"][1] >= 0
    paths = write_episode_pictures(tmp_path, env_config, str(model), seed=0, gif=False)
    assert all(p.is_file() for p in paths)


def test_mcrs_eval_plays_a_run_on_its_evaluation_episodes_beside_every_heuristic(
    run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """``mcrs-eval policy=<run> heuristics=true``: the run's own evaluation episodes (train.eval_seed,
    train.eval_episodes) unless the command names them, so its reward is the one its training logged last;
    every heuristic on the same episodes; tables name the run by its run name, the CSV by its path."""
    import csv

    from hydra import compose, initialize_config_dir

    from mcrs.evaluate import CONFIG_DIR, default_episodes_seed, policy_label, run
    from mcrs.experiment.run.logging import read_scalar_rows, scalar_file

    assert default_episodes_seed([str(run_dir)]) == (2, 1_000_000)  # the suite's tiny eval_episodes
    assert default_episodes_seed(["greedy", "random"]) == (32, 0)
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base=None):
        cfg = compose(
            "eval", overrides=[f"policy={run_dir}", "heuristics=true", "env.max_steps=10", "figures=false"]
        )
    results = run(cfg, tmp_path)
    label = f"{run_dir.name} (qmix)"
    assert policy_label(str(run_dir)) == label
    assert (
        policy_label(str(run_dir / "checkpoints" / "model_000000080.pt")) == f"{run_dir.name}/model_000000080"
    )
    assert list(results) == [str(run_dir), "random", "lawnmower", "greedy", "coverage"]
    logged = read_scalar_rows(scalar_file(run_dir, "eval/episode_reward"))[-1][1]
    assert results[str(run_dir)]["episode_reward"][0] == pytest.approx(logged, abs=1e-4)
    summary = (tmp_path / "summary.md").read_text()
    assert "2 episodes, seed 1000000" in summary
    rows = [line.split("|")[1].strip() for line in summary.splitlines() if line.startswith("| ")]
    assert rows == ["policy", label, "random", "lawnmower", "greedy", "coverage"]
    assert str(run_dir) not in capsys.readouterr().out.split("results in")[0]  # no path in the table
    with open(tmp_path / "metrics.csv") as f:
        assert next(r["policy"] for r in csv.DictReader(f)) == str(run_dir)  # mcrs-report finds the run


def test_a_replay_block_is_named_for_what_it_is(run_dir: Path) -> None:
    from mcrs.experiment.run.checkpoint import CheckpointError

    block = sorted((run_dir / "checkpoints").glob("replay_*.pt"))[0]
    with pytest.raises(
        CheckpointError, match=r"is a block of its run's replay buffer .* pass the run directory"
    ):
        make_policy(str(block), scenario("map10"))
    with pytest.raises(CheckpointError, match=r"is a block of its run's replay buffer"):  # before the bar
        check_policy(str(block), scenario("map10"))


def test_checkpoint_from_another_map_is_refused(run_dir: Path) -> None:
    with pytest.raises(ValueError, match=r"trained on map10.*pass env=map10"):
        make_policy(str(run_dir), scenario("map20"))
    # The same map with a field overridden: the field is the advice (env=map10 is already chosen).
    with pytest.raises(ValueError, match=r"this environment is map10 \(10x10, 3 UAVs\): pass env.n_uavs=4$"):
        make_policy(str(run_dir), scenario("map10", n_uavs=3))
    with pytest.raises(ValueError, match="unknown policy"):
        make_policy("greedyy", scenario("map10"))


def test_mcrs_eval_refuses_another_maps_checkpoint_before_its_progress_bar(
    run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from mcrs.policies.export import export_agent

    capsys.readouterr()
    with pytest.raises(ValueError, match=r"trained on map10.*pass env=map10"):
        evaluate_episodes(scenario("map20", num_envs=2), ["greedy", str(run_dir)], 2, 0, "mcrs-eval")
    shown = capsys.readouterr()
    assert "mcrs-eval" not in shown.out + shown.err  # no bar was started, no episode was played
    export = export_agent(run_dir, tmp_path / "agent.pt2")
    with pytest.raises(ValueError, match=r"exported agent .* trained on map10.*pass env=map10"):
        evaluate_episodes(scenario("map20", num_envs=2), [str(export)], 2, 0, "mcrs-eval")


@pytest.fixture(scope="module")
def far_view_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("far_view_run")
    Experiment(compose_config("train.total_env_steps=80", "env.far_view=2"), path).run()
    return path


def test_a_far_view_checkpoint_is_played_with_the_view_it_was_trained_with(
    far_view_run: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
):
    """``env.far_view`` is what the agent reads, not the task: evaluations, pictures and the ledger play a
    checkpoint with its own value, beside heuristics on the task as given; built directly it is named."""
    from mcrs.policies import policy_env
    from mcrs_lab.analysis.ledger import play

    paper = scenario("map10", max_steps=10)
    with caplog.at_level("WARNING", logger="mcrs.policies"):
        assert policy_env(str(far_view_run), paper) == paper.replace(far_view=2)
    assert (
        "observes with env.far_view=2, as it was trained, whatever this evaluation's env.far_view=0"
        in caplog.text
    )
    assert policy_env("greedy", paper) is paper
    with pytest.raises(
        ValueError, match=r"trained with env.far_view=2; this environment has env.far_view=0: pass "
    ):
        make_policy(str(far_view_run), paper)
    assert evaluate_policy(paper, str(far_view_run), episodes=3, seed=0)["episode_reward"][1] >= 0
    assert all(
        p.is_file() for p in write_episode_pictures(tmp_path, paper, str(far_view_run), seed=0, gif=False)
    )
    assert play(paper, str(far_view_run), episodes=2, seed=0).terms.shape[0] == 2
