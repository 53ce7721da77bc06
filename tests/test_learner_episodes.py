"""A learner and a heuristic compared on the same episodes: the trainer's periodic evaluation plays what
``mcrs-eval`` plays at its seed; the claims pair a learner with a heuristic's score there (one-sample) and
say so where a heuristic played other episodes; the campaign records the heuristics on those episodes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from omegaconf import OmegaConf
from scipy import stats

from mcrs.evaluate import episode_metrics
from mcrs.experiment.training.evaluation import final_metrics
from mcrs.experiment.training.trainer import Experiment
from mcrs.policies import make_policy
from mcrs_lab.analysis.claims import verdict
from mcrs_lab.analysis.evaluations import task_key, training_layout
from mcrs_lab.analysis.pairwise import Samples, bootstrap_ci, pairwise_test
from mcrs_lab.analysis.report import main as report_main
from tests.test_claims import STEPS, claim
from tests.test_report import make_run
from tests.train_helpers import compose_config

ROOT = Path(__file__).resolve().parents[1]
PAPER_MATRIX = ROOT / "mcrs_lab" / "campaign" / "section6_paper.yaml"


def test_the_trainers_evaluation_episodes_are_mcrs_evals_at_its_seed(tmp_path: Path) -> None:
    """``mcrs-eval seed=<train.eval_seed> episodes=<train.eval_episodes>`` on the run's env resets to the
    maps the trainer's periodic evaluation plays, and a heuristic scores the same on both, episode by
    episode."""
    experiment = Experiment(compose_config("env=map10", "train.eval_episodes=3"), tmp_path)
    try:
        seed, episodes = int(experiment.config.train.eval_seed), int(experiment.config.train.eval_episodes)
        from mcrs.env.torchrl_env import MCRSEnv

        experiment.eval_env.set_seed(seed)
        trainer_reset = experiment.eval_env.reset()
        env = MCRSEnv(experiment.env_config.replace(num_envs=episodes))
        env.set_seed(seed)
        eval_reset = env.reset()
        for key in eval_reset.keys(True, True):
            assert torch.equal(trainer_reset.get(key), eval_reset.get(key)), key
        for name in ("greedy", "random"):
            policy = make_policy(name, experiment.env_config.replace(num_envs=episodes), seed)
            trainer_side = final_metrics(experiment.eval_env, policy, seed)
            eval_side = episode_metrics(experiment.env_config, name, episodes, seed)
            assert all(torch.equal(trainer_side[m], eval_side[m]) for m in eval_side), name
    finally:
        experiment.close()


LAYOUT = ("{}", 1_000_000, 32)


def test_a_learner_is_tested_against_a_heuristics_score_on_its_episodes() -> None:
    """One number for the heuristic on the learner's episodes: the one-sample test of the learner's seeds
    against it. The same heuristic evaluated on other seeds only: Welch's test, and said."""
    learner = Samples("qmix", np.array([50.0, 52.0, 51.0]), layouts=frozenset({LAYOUT}))
    other_layout = ("{}", 0, 32)
    on_them = Samples(
        "greedy (heuristic)", np.array([40.0, 49.0]), on_layouts=((LAYOUT, 49.0), (other_layout, 40.0)),
        heuristic=True,
    )  # fmt: skip
    paired = pairwise_test(learner, on_them, "higher")
    assert paired.test == "one-sample" and paired.score == 49.0 and not paired.other_episodes
    assert paired.p == pytest.approx(stats.ttest_1samp([50.0, 52.0, 51.0], 49.0).pvalue)
    assert paired.diff == pytest.approx(2.0) and paired.ci == bootstrap_ci(learner.values, c=49.0)
    assert "one-sample on the same episodes" in paired.text()
    backwards = pairwise_test(on_them, learner, "higher")  # the heuristic named first: the same test
    assert backwards.diff == pytest.approx(-2.0) and backwards.p == paired.p
    assert backwards.ci == (-paired.ci[1], -paired.ci[0])

    elsewhere = Samples(
        "greedy (heuristic)", np.array([40.0, 41.0, 42.0]),
        on_layouts=tuple(((("{}", s, 32), v) for s, v in ((0, 40.0), (1, 41.0), (2, 42.0)))), heuristic=True,
    )  # fmt: skip
    unpaired = pairwise_test(learner, elsewhere, "higher")
    assert unpaired.test == "welch" and unpaired.other_episodes
    assert unpaired.p == pytest.approx(stats.ttest_ind([50, 52, 51], [40, 41, 42], equal_var=False).pvalue)
    assert "heuristic on other episodes" in unpaired.text()
    unknown = pairwise_test(
        Samples("qmix", learner.values), on_them, "higher"
    )  # the learner's episodes unknown
    assert unknown.test == "welch" and unknown.other_episodes

    # a learner level with the heuristic on its episodes is not shown, whatever other seeds say
    level = Samples("qmix", np.array([48.0, 50.0, 49.0]), layouts=frozenset({LAYOUT}))
    result = verdict(
        claim(above=("qmix",), below=("greedy (heuristic)",)), {"qmix": level, "greedy (heuristic)": on_them}
    )
    assert result.word == "not shown" and result.comparisons[0].test == "one-sample"


def _heuristic_result(
    root: Path, name: str, policy: str, env: dict, seed: int, episodes: int, reward: float
) -> None:
    """An ``mcrs-eval`` result folder: metrics.csv and the config it ran (its env)."""
    folder = root / name
    (folder / ".hydra").mkdir(parents=True)
    (folder / ".hydra" / "config.yaml").write_text(
        yaml.safe_dump({"env": env, "seed": seed, "episodes": episodes})
    )
    (folder / "metrics.csv").write_text(
        "policy,env,comm_range,seed,episodes,episode_reward_mean,episode_reward_std\n"
        f"{policy},{env['name']},{env['comm_range']},{seed},{episodes},{reward},1.0\n"
    )


def test_the_claims_table_says_which_heuristic_played_the_learners_episodes(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    for seed in range(3):
        make_run(runs, f"qmix_{seed}", seed=seed, steps=STEPS, reward=[0.0] * 9 + [50.0 + seed] * 2)
    config = OmegaConf.to_container(OmegaConf.load(runs / "qmix_0" / "config.yaml"))
    env, train = config["env"], config["train"]
    # greedy on the learners' episodes (the runs' eval seed and episode count, their env)
    _heuristic_result(runs, "greedy", "greedy", env, train["eval_seed"], train["eval_episodes"], 45.0)
    # coverage on three other evaluation seeds; lawnmower at the learners' seed on another task
    for seed in range(3):
        _heuristic_result(
            runs, f"coverage_{seed}", "coverage", env, seed, train["eval_episodes"], 60.0 + seed
        )
    _heuristic_result(
        runs,
        "lawnmower",
        "lawnmower",
        {**env, "p_detect": 0.5},
        train["eval_seed"],
        train["eval_episodes"],
        40.0,
    )
    claims = tmp_path / "claims.yaml"
    common = {"source": "ours", "paper": "-", "metric": "episode_reward"}
    entries = [
        {**common, "claim": f"qmix beats {h}", "above": ["qmix"], "below": [f"{h} (heuristic)"]}
        for h in ("greedy", "coverage", "lawnmower")
    ]
    claims.write_text(yaml.safe_dump({"map10": entries}))
    out = tmp_path / "report"
    assert report_main([str(runs), "--out", str(out), "--claims", str(claims)]) == 0
    rows = {
        r[1].strip(): r
        for r in (line.split("|")[1:-1] for line in (out / "claims.md").read_text().splitlines()[2:])
    }
    greedy = rows["qmix beats greedy"]
    assert "greedy (heuristic) 45.00 on the learners' episodes" in greedy[4]
    assert "one-sample on the same episodes" in greedy[5] and greedy[2].strip().startswith("**reproduced**")
    coverage = rows["qmix beats coverage"]
    assert (
        "coverage (heuristic) 61.00 ± 1.00 (3) over evaluation seeds, not the learners' episodes"
        in coverage[4]
    )
    assert "heuristic on other episodes" in coverage[5] and "p " in coverage[5] and "→" in coverage[5]
    assert coverage[2].strip().startswith("**not reproduced**")
    lawnmower = rows["qmix beats lawnmower"]  # the same seed on another task is not the learners' episodes
    assert "not the learners' episodes" in lawnmower[4] and "one number on a side: no test" in lawnmower[5]


def test_a_heuristic_with_no_learner_beside_it_gives_its_numbers_alone(tmp_path: Path) -> None:
    """Before a map's learners have run, the claims table shows the heuristic's score and says nothing of
    whose episodes it played: there are no learner's episodes to hold it against yet."""
    runs = tmp_path / "runs"
    make_run(runs, "qmix_0", steps=STEPS)
    config = OmegaConf.to_container(OmegaConf.load(runs / "qmix_0" / "config.yaml"))
    evals = tmp_path / "evals"
    env, train = config["env"], config["train"]
    _heuristic_result(evals, "greedy", "greedy", env, train["eval_seed"], train["eval_episodes"], 45.0)
    claims = tmp_path / "claims.yaml"
    entry = {"source": "ours", "paper": "-", "metric": "episode_reward", "claim": "qmix beats greedy"}
    claims.write_text(
        yaml.safe_dump({"map10": [entry | {"above": ["qmix"], "below": ["greedy (heuristic)"]}]})
    )
    out = tmp_path / "report"
    assert report_main([str(evals), "--out", str(out), "--claims", str(claims)]) == 0
    (row,) = [line.split("|")[1:-1] for line in (out / "claims.md").read_text().splitlines()[2:]]
    assert row[4].strip().endswith("greedy (heuristic) 45.00 (1)"), row[4]
    assert row[2].strip() == "**not run**: no runs of qmix"


def test_the_layout_of_a_run_and_of_an_evaluation_name_the_task_seed_and_episodes() -> None:
    env = {"name": "map20", "comm_range": 5, "width": 20}
    assert task_key(env) == task_key({**env, "comm_range": 5.0, "expose_beliefs": True, "far_view": 3})
    assert task_key(env) != task_key({**env, "discovery_rule": "belief"})  # legacy: target
    assert task_key(None) is None
    config = {"env": env, "train": {"eval_seed": 1_000_000, "eval_episodes": 32}}
    assert training_layout(config) == (task_key(env), 1_000_000, 32)
    assert training_layout({"env": env, "train": {}}) is None


def test_section6_paper_records_the_heuristics_on_the_learners_episodes() -> None:
    """The campaign's heuristics evaluation plays budget=campaign's evaluation episodes, evaluates no
    trained point, and its records are committed for every map of figures 6 and 7."""
    from mcrs_lab.campaign.evaluations import load_evaluations, plan
    from mcrs_lab.campaign.matrix import load_matrix

    points, titles = load_matrix(PAPER_MATRIX)
    (heuristics,) = [e for e in load_evaluations(PAPER_MATRIX, set(titles)) if e.name == "heuristics"]
    train = compose_config("budget=campaign", tiny=False).train
    assert heuristics.seeds == (train.eval_seed,) and heuristics.episodes == train.eval_episodes
    assert not heuristics.trained and heuristics.variants == (("default", ()),)
    jobs, left_out = plan([heuristics], points, ROOT / "results" / "records" / "paper")
    assert left_out == [] and {j.policy for j in jobs} == {"random", "lawnmower", "greedy", "coverage"}
    assert sorted({j.env for j in jobs}) == ["map10", "map15", "map20"] and len(jobs) == 12
    assert all(job.recorded(ROOT / "results" / "records" / "paper") for job in jobs)
    record = json.loads(
        (ROOT / "results/records/paper/heuristics/default/eval/map20/greedy_rc5_seed1000000.json").read_text()
    )
    assert (
        record["rows"][0]["seed"] == train.eval_seed and record["rows"][0]["episodes"] == train.eval_episodes
    )


def test_a_heuristics_only_evaluation_evaluates_no_trained_point(tmp_path: Path) -> None:
    """``trained: false``: the heuristics on the maps of ``of`` and nothing else, whatever points are
    finished; it must name heuristics, and takes true or false only."""
    from mcrs_lab.campaign.evaluations import load_evaluations, plan
    from mcrs_lab.campaign.matrix import MatrixError, load_matrix
    from tests.test_campaign import TWO_POINTS

    matrix = tmp_path / "m.yaml"
    entry = "evaluations:\n  h:\n    of: [figa]\n    heuristics: [greedy, coverage]\n    seeds: [1000000]\n"
    entry += "    variants: {default: []}\n"
    matrix.write_text(TWO_POINTS + entry + "    trained: false\n")
    points, titles = load_matrix(matrix)
    (evaluation,) = load_evaluations(matrix, set(titles))
    jobs, left_out = plan([evaluation], points, tmp_path / "records")
    assert [j.policy for j in jobs] == ["greedy", "coverage"] and left_out == []
    assert "seed=1000000" in jobs[0].command(tmp_path / "outputs")
    matrix.write_text(TWO_POINTS + entry)  # the default: the trained points too (none finished here)
    (evaluation,) = load_evaluations(matrix, set(titles))
    assert len(plan([evaluation], points, tmp_path / "records")[1]) == len(points)
    for bad, message in (("    trained: nope\n", "trained='nope': true or false"),):
        matrix.write_text(TWO_POINTS + entry + bad)
        with pytest.raises(MatrixError, match=message):
            load_evaluations(matrix, set(titles))
    matrix.write_text(TWO_POINTS + entry.replace("[greedy, coverage]", "[]") + "    trained: false\n")
    with pytest.raises(MatrixError, match="trained: false needs heuristics"):
        load_evaluations(matrix, set(titles))
