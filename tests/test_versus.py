"""Learners against the heuristics (mcrs_lab.analysis.versus): the verdict at the end, the step from
which a learner is better, on metrics that are better higher or lower."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from mcrs.viz.learning_curves import curve_of
from mcrs_lab.analysis.evaluations import task_key
from mcrs_lab.analysis.runs import EvaluationRow
from mcrs_lab.analysis.versus import better_since, versus, versus_evaluated, versus_table

STEPS = np.arange(0, 110, 10)  # evaluations at 0, 10, ..., 100 of a budget of 100


def _curve(*seeds: list[float], steps: np.ndarray = STEPS):
    return curve_of("m", [(steps, np.asarray(s, dtype=float)) for s in seeds])


def test_better_since_is_the_last_crossing_of_the_smoothed_mean() -> None:
    crossing = _curve([0, 1, 2, 3, 6, 6, 6, 6, 6, 6, 6])
    assert better_since(crossing, 5.0, "higher", window=1) == 40  # no smoothing: the first step above
    assert better_since(crossing, 5.0, "higher", window=20) == 50  # (3 + 6) / 2 = 4.5 at 40: not yet
    back_and_forth = _curve([0, 6, 6, 1, 6, 6, 1, 6, 6, 6, 6])
    assert better_since(back_and_forth, 5.0, "higher", window=1) == 70
    assert better_since(_curve([0, 6, 6, 6, 6, 6, 6, 6, 6, 6, 4]), 5.0, "higher", window=1) is None
    # lower is better (collisions): the curve falls below the heuristic's mean
    assert better_since(_curve([9, 9, 9, 2, 2, 2, 2, 2, 2, 2, 2]), 3.0, "lower", window=1) == 30


def test_the_untrained_evaluation_at_step_0_does_not_hold_back_the_date() -> None:
    learner = _curve([-100, 6, 6, 6, 6, 6, 6, 6, 6, 6, 6])
    assert better_since(learner, 5.0, "higher", window=50) == 10  # step 0 is outside every later window
    assert better_since(_curve([6] * 11), 5.0, "higher", window=50) == 0  # better from the start


def _rows(policy: str, metric: str, values: list[float]) -> list[EvaluationRow]:
    return [
        EvaluationRow(Path(f"/eval/{policy}{k}"), policy, "map20", 5.0, k, 32, {metric: v})
        for k, v in enumerate(values)
    ]


def test_versus_judges_every_learner_against_every_heuristic() -> None:
    good = _curve(*([0, 1, 2, 3, 6, 6, 6, 6, 6, 6, 6 + d] for d in (0.1, 0.2, 0.3)))
    bad = _curve(*([0, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1 + d] for d in (0.1, 0.2, 0.3)))
    short = _curve([0, 6, 6, 6], [0, 6, 6, 7], steps=STEPS[:4])
    curves = {
        "eval/episode_reward": {"good": good, "bad": bad, "short": short},
        "eval/collisions": {"good": _curve(*([30, 9, 9, 9, 9, 9, 9, 9, 9, 9, 9 + d] for d in (0.1, 0.3)))},
    }
    evaluations = [
        *_rows("greedy", "episode_reward", [4.9, 5.0, 5.1]),
        *_rows("coverage", "episode_reward", [5.9, 6.1, 6.2]),
        *_rows("greedy", "collisions", [20.0, 21.0, 22.0]),
    ]
    results = {
        (r.metric, r.method, r.heuristic): r
        for r in versus(curves, ["good", "bad", "short"], evaluations, 5.0, 100)
    }
    win = results["episode_reward", "good", "greedy (heuristic)"]
    assert (win.outcome, win.since) == ("better", 40)  # a tenth of the budget holds one evaluation here
    assert win.p < 0.05 and win.heuristic_mean == pytest.approx(5.0)
    assert results["episode_reward", "bad", "greedy (heuristic)"].outcome == "worse"
    assert results["episode_reward", "good", "coverage (heuristic)"].outcome == "level"
    assert results["episode_reward", "short", "greedy (heuristic)"].outcome == "unfinished"
    fewer = results["collisions", "good", "greedy (heuristic)"]  # collisions: lower is better
    assert (fewer.outcome, fewer.since) == ("better", 10)
    assert ("collisions", "good", "coverage (heuristic)") not in results  # coverage has no collisions here

    rows, md = versus_table(list(results.values()))
    lines = [[c.strip() for c in line.strip("|").split("|")] for line in md.splitlines()]
    assert lines[0] == ["metric", "method", "greedy", "coverage"]
    by_method = {tuple(line[:2]): line[2:] for line in lines[2:]}
    assert by_method["episode reward", "good"][0] == f"**better** (p = {win.p:.3f}, other episodes) from 40"
    assert by_method["episode reward", "short"] == ["not run to the end", "not run to the end"]
    assert by_method["collisions", "good"][1] == "-"
    assert {(r["metric"], r["method"], r["heuristic"], r["outcome"]) for r in rows} >= {
        ("episode_reward", "bad", "greedy (heuristic)", "worse")
    }


def test_a_heuristic_on_the_learners_own_episodes_is_one_score_the_seeds_are_tested_against() -> None:
    """The heuristic played the learners' evaluation episodes once: a Welch test would have one number on
    its side (no test); the seeds are tested against its score on those episodes instead."""
    env = {"name": "map20"}
    layout = (task_key(env), 1_000_000, 32)
    assert layout[0] is not None
    heuristic = EvaluationRow(
        Path("/eval/greedy"), "greedy", "map20", 5.0, 1_000_000, 32, {"episode_reward": 5.0}, env=env
    )
    good = _curve(*([0, 1, 2, 3, 6, 6, 6, 6, 6, 6, 6 + d] for d in (0.1, 0.2, 0.3)))
    curves = {"eval/episode_reward": {"good": good}}
    (paired,) = versus(curves, ["good"], [heuristic], 5.0, 100, {"good": frozenset({layout})})
    assert (paired.outcome, paired.test, paired.heuristic_mean, paired.since) == (
        "better",
        "one-sample",
        5.0,
        40,
    )
    window_means = [6.05, 6.1, 6.15]  # each seed over the last tenth: its evaluations at 90 and 100
    assert paired.p == pytest.approx(stats.ttest_1samp(window_means, 5.0).pvalue)
    assert paired.text() == f"**better** (p = {paired.p:.3f}) from 40"
    other = (task_key({"name": "map20", "comm_range": 3}), 1_000_000, 32)  # another task: other episodes
    (unpaired,) = versus(curves, ["good"], [heuristic], 5.0, 100, {"good": frozenset({other})})
    assert (unpaired.outcome, unpaired.test) == ("one seed", "none")


def test_trained_policies_on_fixed_episodes_count_one_sample_per_training_run() -> None:
    """mcrs-eval of finished runs (3 training seeds x 2 evaluation seeds) against a heuristic: each run is
    its mean over the evaluation seeds, Welch over the runs; no date (no learning curve)."""
    rows = _rows("greedy", "episode_reward", [379.5, 379.8, 380.1])
    for run, scores in enumerate(([381.0, 382.0], [383.0, 382.0], [382.5, 381.5])):
        for seed, score in enumerate(scores):
            rows.append(
                EvaluationRow(
                    Path(f"/eval/run{run}/{seed}"),
                    f"outputs/shields_gamma/map20_qmix_seed{run}",
                    "map20",
                    5.0,
                    seed,
                    32,
                    {"episode_reward": score},
                )
            )
    (result,) = versus_evaluated(rows)
    assert (result.method, result.heuristic, result.outcome, result.since) == (
        "trained map20_qmix",
        "greedy (heuristic)",
        "better",
        None,
    )
    assert result.method_mean == pytest.approx(382.0) and result.p < 0.05
    one_run = [r for r in rows if "seed0" in r.policy or r.is_heuristic]
    assert [r.outcome for r in versus_evaluated(one_run)] == ["one seed"]
