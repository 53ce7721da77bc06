"""mcrs-eval: the pure evaluation function, the table and the Hydra command line."""

from __future__ import annotations

import csv
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from mcrs.env import METRICS, scenario
from mcrs.env.config import from_mapping
from mcrs.evaluate import CONFIG_DIR, episode_metrics, evaluate_policy, format_table, policy_names, run
from tests.device_helpers import available_devices

TINY = ["episodes=2", "figures=false", "env.max_steps=5"]


@pytest.mark.parametrize("policy", ["random", "lawnmower", "greedy", "coverage"])
def test_evaluate_policy_returns_every_metric(policy: str) -> None:
    cfg = scenario("map10", max_steps=20)
    result = evaluate_policy(cfg, policy, episodes=5, seed=1)
    assert list(result) == list(METRICS)
    for name, (mean, std) in result.items():
        assert math.isfinite(mean) and math.isfinite(std) and std >= 0, name
    assert 0 < result["coverage"][0] <= 1
    assert result["uncertainty"][0] < cfg.n_cells  # sensing removed some uncertainty
    assert result == evaluate_policy(cfg, policy, episodes=5, seed=1)  # reproducible


def test_evaluate_policy_takes_the_composed_configs_scenario() -> None:
    import mcrs

    scenario_node = mcrs.compose("env=map10", "env.max_steps=6").env  # what a user holds: config.env
    assert evaluate_policy(scenario_node, "greedy", 3, 0) == evaluate_policy(
        scenario("map10", max_steps=6), "greedy", 3, 0
    )
    with pytest.raises(TypeError, match=r"env_config: expected an EnvConfig .* got str"):
        evaluate_policy("map10", "greedy", 3, 0)  # type: ignore[arg-type]


def test_episode_metrics_chunks_and_single_episode() -> None:
    cfg = scenario("map10", max_steps=6)
    values = episode_metrics(cfg, "random", episodes=7, seed=0, max_batch=3)
    assert all(v.shape == (7,) for v in values.values())
    assert values["episode_reward"].unique().numel() > 1  # chunks are different episodes
    assert evaluate_policy(cfg, "greedy", episodes=1, seed=0)["coverage"][1] == 0.0
    with pytest.raises(ValueError, match="episodes"):
        episode_metrics(cfg, "random", episodes=0, seed=0)


@pytest.mark.parametrize("device", available_devices())
def test_episode_metrics_come_back_on_the_cpu_from_any_env_device(device: str) -> None:
    """CSV rows, numpy statistics and figures are made from them: an env on CUDA must not leak its device."""
    cfg = scenario("map10", max_steps=6, device=device)
    values = episode_metrics(cfg, "greedy", episodes=3, seed=0)
    assert all(v.device.type == "cpu" and v.shape == (3,) for v in values.values())
    assert values["uncertainty"].numpy().max() < cfg.n_cells  # a numpy view works
    assert evaluate_policy(cfg, "greedy", episodes=3, seed=0)["coverage"][0] > 0


def test_format_table_is_aligned_markdown() -> None:
    results = {
        "random": {m: (1.0, 0.5) for m in METRICS},
        "lawnmower": {m: (123.456, 10.0) for m in METRICS},
    }
    lines = format_table(results).splitlines()
    assert len(lines) == 4 and len({len(line) for line in lines}) == 1
    assert lines[0].startswith("| policy") and "episode reward" in lines[0] and "coverage" in lines[0]
    assert set(lines[1]) <= set("|-:")
    assert "123.46 ± 10.00" in lines[3]


def test_policy_names() -> None:
    assert policy_names("all") == ["random", "lawnmower", "greedy", "coverage"]
    assert policy_names("greedy", heuristics=True) == ["greedy", "random", "lawnmower", "coverage"]
    assert policy_names("greedy") == ["greedy"]
    with pytest.raises(
        ValueError, match=r"unknown policy 'bogus'; allowed: .*greedy.*lawnmower.*random.*all"
    ):
        policy_names("bogus")
    with pytest.raises(
        ValueError,
        match=r"unknown policy 'greedyy'; allowed: greedy, coverage, .*, or a checkpoint .* exported agent",
    ):
        policy_names("greedyy")  # the closest first


def _compose(overrides: list[str]):
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base=None):
        return compose("eval", overrides=overrides)


def test_hydra_config_composes_with_overrides() -> None:
    cfg = _compose([])
    # episodes and seed unset: a trained policy's own evaluation episodes, else 32 of seed 0
    assert (cfg.policy, cfg.heuristics, cfg.episodes, cfg.seed, cfg.figures) == (
        "greedy",
        False,
        None,
        None,
        True,
    )
    assert from_mapping(cfg.env) == scenario("map10")
    cfg = _compose(["env=map20", "env.comm_range=0", "policy=lawnmower", "episodes=8"])
    env = from_mapping(cfg.env)
    assert (env.name, env.n_uavs, env.comm_range, cfg.policy, cfg.episodes) == (
        "map20",
        10,
        0.0,
        "lawnmower",
        8,
    )


def test_run_in_process_writes_results(tmp_path: Path, capsys) -> None:
    cfg = _compose(["policy=all", "env.max_steps=4", "episodes=3", "figures=true"])
    results = run(cfg, tmp_path)
    assert list(results) == ["random", "lawnmower", "greedy", "coverage"]
    printed = capsys.readouterr().out
    assert "| policy" in printed and "| greedy" in printed and "false discoveries" in printed
    with open(tmp_path / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["policy"] for r in rows] == ["random", "lawnmower", "greedy", "coverage"]
    assert {(r["env"], r["comm_range"], r["seed"]) for r in rows} == {
        ("map10", "5", "0")
    }  # mcrs-report groups; heuristics alone: seed 0 unless seed= says
    assert float(rows[2]["episode_reward_mean"]) == pytest.approx(
        results["greedy"]["episode_reward"][0], rel=1e-5
    )
    with open(tmp_path / "episodes.csv") as f:
        assert len(list(csv.DictReader(f))) == 4 * 3
    summary = (tmp_path / "summary.md").read_text()
    assert "| lawnmower" in summary
    assert (
        "mean ± standard deviation over the episodes" in summary and "lower for final uncertainty" in summary
    )
    for policy in results:
        for name in ("scene.png", "uncertainty_contours.png", "episode.gif"):
            assert (tmp_path / policy / name).stat().st_size > 1000


def test_threads_sets_torchs_threads_and_a_bad_value_is_refused(tmp_path: Path) -> None:
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        run(_compose(["threads=1", "figures=false", *TINY]), tmp_path / "one")
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)
    with pytest.raises(ValueError, match=r"threads=x: allowed values are auto .*, 0 .* or 1 to"):
        run(_compose(["threads=x", *TINY]), tmp_path / "bad")
    assert not (tmp_path / "bad" / "metrics.csv").exists()


def test_run_rejects_unknown_policy(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"allowed: .*greedy"):
        run(_compose(["policy=bogus", *TINY]), tmp_path)
    assert not (tmp_path / "metrics.csv").exists()


@pytest.mark.parametrize("where", ["missing", "empty_run", "missing.pt"])
def test_run_rejects_a_policy_path_without_a_checkpoint_before_any_episode(
    where: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A mistyped run directory is named at once, not after a progress bar has started."""
    (tmp_path / "empty_run").mkdir()
    policy = tmp_path / where
    with pytest.raises(ValueError, match=rf"policy={policy}: no checkpoint there .*'greedy'"):
        run(_compose([f"policy={policy}", *TINY]), tmp_path / "out")
    assert "steps" not in capsys.readouterr().out  # no episode was started
    assert not (tmp_path / "out" / "metrics.csv").exists()


def _cli(tmp_path: Path, *overrides: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "HYDRA_FULL_ERROR": "0"}
    return subprocess.run(
        [sys.executable, "-m", "mcrs.evaluate", f"hydra.run.dir={tmp_path}", *overrides],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
        cwd=tmp_path,
    )


@pytest.mark.slow
def test_cli_runs_and_prints_table(tmp_path: Path) -> None:
    done = _cli(tmp_path, *TINY, "policy=lawnmower", "env=map15", "env.comm_range=0")
    assert done.returncode == 0, done.stderr
    assert "map15" in done.stdout and "R_c=0" in done.stdout and "| lawnmower" in done.stdout
    assert (tmp_path / "metrics.csv").is_file() and (tmp_path / "summary.md").is_file()
    assert not (tmp_path / "scene.png").exists()  # figures=false


@pytest.mark.slow
def test_cli_unknown_policy_lists_allowed_names(tmp_path: Path) -> None:
    done = _cli(tmp_path, *TINY, "policy=bogus")
    assert done.returncode != 0
    assert "unknown policy 'bogus'" in done.stderr and "lawnmower" in done.stderr


@pytest.mark.slow
def test_cli_bad_env_field_is_one_clear_message_without_traceback(tmp_path: Path) -> None:
    done = _cli(tmp_path, *TINY, "env.comm_range=-1", "env.p_detect=2")
    assert done.returncode != 0
    assert "mcrs-eval: error: invalid environment config" in done.stderr
    assert "comm_range=-1.0: must be a distance >= 0" in done.stderr and "p_detect=2" in done.stderr
    assert "Traceback" not in done.stderr


@pytest.mark.slow
def test_evaluations_started_together_get_their_own_directories(tmp_path: Path) -> None:
    """Two ``mcrs-eval`` started in the same second: two directories (the names carry the process id),
    each with its own complete results."""
    env = {**os.environ, "HYDRA_FULL_ERROR": "0"}
    command = [sys.executable, "-m", "mcrs.evaluate", *TINY, "policy=random"]
    procs = [
        subprocess.Popen(
            command, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        for _ in range(2)
    ]
    for proc in procs:
        _, err = proc.communicate(timeout=300)
        assert proc.returncode == 0, err
    runs = sorted((tmp_path / "outputs" / "eval").iterdir())
    assert len(runs) == 2, runs
    assert {run.name.rsplit("_", 1)[1] for run in runs} == {str(proc.pid) for proc in procs}
    for run_dir in runs:
        with open(run_dir / "metrics.csv") as f:
            assert [row["policy"] for row in csv.DictReader(f)] == ["random"]


def test_a_trained_runs_evaluation_and_rendering_go_into_the_run(tmp_path: Path) -> None:
    """``policy=<run>`` (or one of its checkpoints): the results stay with the run, not in a stray folder."""
    import mcrs.render_episode  # noqa: F401  (registers the render schema)
    from mcrs.experiment.run.rundir import beside_run, register_resolvers

    run_dir = tmp_path / "outputs" / "map10" / "qmix" / "run"
    (run_dir / "checkpoints").mkdir(parents=True)
    (run_dir / "config.yaml").write_text("seed: 0\n")
    weights = run_dir / "checkpoints" / "model_000000040.pt"
    assert beside_run(str(run_dir), "eval", "outputs/eval") == str(run_dir / "eval")
    assert beside_run(str(weights), "render", "outputs/render") == str(run_dir / "render")
    assert beside_run("greedy", "eval", "outputs/eval") == "outputs/eval"
    assert beside_run(str(tmp_path / "elsewhere.pt"), "eval", "outputs/eval") == "outputs/eval"
    register_resolvers()
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base=None):
        cfg = compose(config_name="eval", overrides=[f"policy={run_dir}"], return_hydra_config=True)
        render = compose(config_name="render", overrides=[f"policy={run_dir}"])
    assert str(cfg.hydra.run.dir).startswith(f"{run_dir / 'eval'}/")
    assert str(cfg.hydra.run.dir).endswith(f"_{os.getpid()}")
    assert str(render.out).startswith(f"{run_dir / 'render'}/") and str(render.out).endswith(
        f"_{os.getpid()}"
    )
