"""The paper's claims judged on runs (mcrs_lab.analysis.claims): the windows, the test, the verdicts, the file."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy import stats

from mcrs.policies import POLICIES
from mcrs.viz.learning_curves import Curve
from mcrs_lab.analysis.claims import (
    CLAIM_Q_TOT,
    Claim,
    ClaimsError,
    default_claims_path,
    load_claims,
    verdict,
    window_samples,
)
from mcrs_lab.analysis.pairwise import (
    BOOTSTRAP_SEED,
    Samples,
    bootstrap_ci,
    compare,
    hedges_correction,
    hedges_g,
    holm,
)
from mcrs_lab.analysis.report import main as report_main
from mcrs_lab.analysis.report_training import ALGO_ORDER
from tests.test_report import make_evaluation, make_run

STEPS = list(range(0, 110_000, 10_000))  # 0 .. 100k: "end" is 90k and 100k, "start" is 10k .. 30k


def claim(**fields: object) -> Claim:
    base = dict(
        claim="a beats b",
        source="fig. 0",
        paper="-",
        metric="episode_reward",
        better="higher",
        window="end",
        above=("a",),
        below=("b",),
    )
    return Claim(**{**base, **fields})


def samples(label: str, *values: float, complete: bool = True) -> Samples:
    return Samples(label, np.array(values, dtype=float), complete)


def test_windows_average_each_seed_over_its_evaluations() -> None:
    steps = np.array(STEPS)
    values = np.stack([np.arange(11.0), 10 * np.arange(11.0)])  # two seeds
    curve = Curve("a", steps, values.mean(0), values.std(0, ddof=1), np.zeros(11), values)
    end = window_samples(curve, "end", budget=100_000)
    assert end.values.tolist() == [9.5, 95.0] and end.complete  # 90k and 100k
    start = window_samples(curve, "start", budget=100_000)
    assert start.values.tolist() == [2.0, 20.0]  # 10k, 20k, 30k: step 0 (untrained) is left out
    short = window_samples(curve, "end", budget=200_000)  # a run stopped at half the budget
    assert not short.complete and len(short.values) == 0


def test_compare_is_welchs_test_in_the_claims_direction() -> None:
    a, b = samples("a", 10, 11, 12), samples("b", 1, 2, 3)
    outcome, p = compare(a, b, "higher")
    assert outcome == "holds" and p == pytest.approx(
        stats.ttest_ind([10, 11, 12], [1, 2, 3], equal_var=False).pvalue
    )
    assert compare(a, b, "lower")[0] == "reversed"  # fewer collisions is better: a has more
    assert compare(samples("a", 1, 5, 9), samples("b", 2, 4, 6), "higher")[0] == "noise"
    assert compare(samples("a", 100.0), b, "higher") == ("few", pytest.approx(np.nan, nan_ok=True))


def test_compare_against_a_constant_is_welchs_limit_without_a_warning() -> None:
    """A heuristic that scores the same on every evaluation seed (coverage 0.975): Welch's test with one
    variance zero, t = (mean - c) / (sd / sqrt(n)) on n - 1 degrees of freedom, and no scipy warning of
    catastrophic cancellation (which its two-sample moments of a constant sample raise)."""
    learner = np.array([0.99181107, 0.9968395, 0.99570311])
    t = (learner.mean() - 0.975) / (learner.std(ddof=1) / np.sqrt(3))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        outcome, p = compare(samples("a", *learner), samples("b", 0.975, 0.975, 0.975), "higher")
        assert compare(samples("b", 0.975, 0.975, 0.975), samples("a", *learner), "higher")[0] == "reversed"
    assert outcome == "holds" and p == pytest.approx(2 * stats.t.sf(t, df=2))


def test_verdicts_of_all_and_any() -> None:
    good, bad, wide = samples("a", 10, 11, 12), samples("b", 1, 2, 3), samples("c", 0, 6, 12)
    assert verdict(claim(), {"a": good, "b": bad}).word == "reproduced"
    flipped = verdict(claim(), {"a": bad.__class__("a", bad.values), "b": good.__class__("b", good.values)})
    assert flipped.word == "not reproduced" and "b significantly higher than a" in flipped.why
    assert verdict(claim(below=("c",)), {"a": good, "c": wide}).word == "not shown"
    one = verdict(claim(), {"a": samples("a", 50.0), "b": bad})
    assert one.word == "not shown" and "one seed of a" in one.why
    assert verdict(claim(), {"a": good}).word == "not run"  # b has no runs
    partial = verdict(claim(), {"a": samples("a", 10, 11, complete=False), "b": bad})
    assert partial.word == "not run" and "a not run to the end" in partial.why

    # any: one learner beating the heuristic is enough, a partial one does not count
    greedy = samples("greedy (heuristic)", 5, 6, 7)
    q = claim(quantifier="any", above=("a", "b", "x"), below=("greedy (heuristic)",))
    found = verdict(q, {"a": good, "b": bad, "greedy (heuristic)": greedy})
    assert (
        found.word == "reproduced"
        and found.why.startswith("significantly higher after Holm: a (Holm p = 0.0")
        and "no runs of x" in found.why
    )
    none = verdict(q, {"a": samples("a", 0, 1, 2), "b": bad, "greedy (heuristic)": greedy})
    assert none.word == "not shown" and "no runs of x" in none.why  # x might still do it
    q_run = claim(quantifier="any", above=("a", "b"), below=("greedy (heuristic)",))
    assert (
        verdict(q_run, {"a": samples("a", 0, 1, 2), "b": bad, "greedy (heuristic)": greedy}).word
        == "not reproduced"
    )
    mixed = verdict(q, {"a": samples("a", 0, 1, 2), "b": samples("b", 9.0), "greedy (heuristic)": greedy})
    assert mixed.word == "not shown" and "b: one seed" in mixed.why


def test_claims_file_errors_name_the_field(tmp_path: Path) -> None:
    path = tmp_path / "claims.yaml"
    entry = {
        "claim": "x",
        "source": "s",
        "paper": "p",
        "metric": "episode_reward",
        "above": ["a"],
        "below": ["b"],
    }
    path.write_text(yaml.safe_dump({"map10": [entry]}))
    assert load_claims(path, "map10")[0].window == "end"
    assert load_claims(path, "map15") == []  # no claims about that map
    for bad, message in (
        ({**entry, "window": "middle"}, "window='middle'; allowed: end, start"),
        ({**entry, "better": "more"}, "better='more'; allowed: higher, lower"),
        ({**entry, "colour": 1}, "unknown field(s) colour"),
        ({k: v for k, v in entry.items() if k != "below"}, "missing field 'below'"),
        ({**entry, "above": []}, "'above' must be a non-empty list"),
    ):
        path.write_text(yaml.safe_dump({"map10": [bad]}))
        with pytest.raises(ClaimsError, match=message.replace("(", r"\(").replace(")", r"\)")):
            load_claims(path, "map10")


def test_the_papers_claims_name_real_methods() -> None:
    """A typo in paper_claims.yaml would silently read as "not run"."""
    known = {*ALGO_ORDER, *(f"{name} (heuristic)" for name in POLICIES)}
    for env in ("map10", "map15", "map20"):
        claims = load_claims(default_claims_path(), env)
        assert claims, env
        for c in claims:
            for label in (*c.above, *c.below):
                assert label.split(" ")[0] in known or label in known, (env, label)


def test_report_writes_the_claims_table(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    for seed in range(3):  # qmix clearly above greedy at the end; vdn level with it
        make_run(runs, f"qmix_{seed}", seed=seed, steps=STEPS, reward=[0.0] * 9 + [50.0 + seed, 52.0 + seed])
        make_run(
            runs, f"vdn_{seed}", algo="vdn", seed=seed, steps=STEPS, reward=[0.0] * 9 + [30.0 + 9 * seed] * 2
        )
        make_evaluation(runs, f"greedy_{seed}", "greedy", 5.0, seed, found=4 + 0.1 * seed)  # reward 40-42
    claims = tmp_path / "claims.yaml"
    common = {"source": "ours", "paper": "-", "metric": "episode_reward"}
    claims.write_text(
        yaml.safe_dump(
            {
                "map10": [
                    {
                        **common,
                        "claim": "qmix beats greedy",
                        "above": ["qmix"],
                        "below": ["greedy (heuristic)"],
                        "ours": True,
                    },
                    {
                        **common,
                        "claim": "vdn beats greedy",
                        "above": ["vdn"],
                        "below": ["greedy (heuristic)"],
                    },
                    {**common, "claim": "emc beats qmix", "above": ["emc"], "below": ["qmix"]},
                ]
            }
        )
    )
    out = tmp_path / "report"
    assert report_main([str(runs), "--out", str(out), "--claims", str(claims)]) == 0
    rows = [line.split("|")[1:-1] for line in (out / "claims.md").read_text().splitlines()[2:]]
    verdicts = {r[1].strip(): r[2].strip() for r in rows}
    assert verdicts["qmix beats greedy"].startswith(
        "**yes**: every comparison significant after Holm"
    )  # our question
    assert verdicts["vdn beats greedy"].startswith(
        "**not shown**: vdn against greedy (heuristic) within noise"
    )
    assert verdicts["emc beats qmix"] == "**not run**: no runs of emc"
    assert "qmix 52.00 ± 1.00 (3)" in rows[0][4]  # (50 + 52) / 2 + seed, averaged over the seeds


def test_a_claim_on_the_mean_q_tot_reads_the_training_scalar(tmp_path: Path) -> None:
    """Figure 8b's claim is on Q_tot, which runs log while training (train/q_taken_mean), not evaluate."""
    runs = tmp_path / "runs"
    for seed in range(3):
        high = [100.0 + seed] * len(STEPS)
        make_run(runs, f"emu_change_{seed}", algo="emu_change", seed=seed, steps=STEPS, q_tot=high)
        make_run(runs, f"qmix_{seed}", seed=seed, steps=STEPS, q_tot=[10.0 + seed] * len(STEPS))
    claims = tmp_path / "claims.yaml"
    entry = {
        "source": "fig. 8b",
        "paper": "-",
        "metric": CLAIM_Q_TOT,
        "claim": "Q_tot",
        "above": ["emu_change"],
    }
    claims.write_text(yaml.safe_dump({"map10": [{**entry, "below": ["qmix"]}]}))
    out = tmp_path / "report"
    assert report_main([str(runs), "--out", str(out), "--claims", str(claims)]) == 0
    row = (out / "claims.md").read_text().splitlines()[2].split("|")[1:-1]
    assert (
        row[4]
        .strip()
        .startswith("mean Q_tot of replayed transitions, last tenth: emu_change 101.00 ± 1.00 (3)")
    )
    assert row[2].strip().startswith("**reproduced**")


def test_a_bad_claims_file_is_one_line(tmp_path: Path) -> None:
    make_run(tmp_path / "runs", "qmix_0")
    bad = tmp_path / "claims.yaml"
    bad.write_text("map10: [{claim: x}]")
    with pytest.raises(
        SystemExit, match=r"mcrs-report: error: --claims: .*map10\[0\]: missing field 'source'"
    ):
        report_main([str(tmp_path / "runs"), "--out", str(tmp_path / "out"), "--claims", str(bad)])


def test_a_pattern_claim_on_evaluations_of_trained_policies(tmp_path: Path) -> None:
    """``trained *`` stands for every trained policy of an evaluation-only report; each trained run is
    one number (its mean over the evaluation seeds)."""
    evals = tmp_path / "evals"
    for seed in range(3):
        make_evaluation(evals, f"greedy_{seed}", "greedy", 5.0, seed, found=4 + 0.1 * seed)  # 40, 41, 42
        for run, found in (("qmix_seed0", 5.0), ("qmix_seed1", 5.2)):  # 50 and 52 on every seed
            make_evaluation(evals, f"{run}_{seed}", f"outputs/x/{run}", 5.0, seed, found=found)
    claims = tmp_path / "claims.yaml"
    entry = {"claim": "a trained policy beats greedy", "source": "ours", "paper": "-", "ours": True}
    entry |= {"metric": "episode_reward", "quantifier": "any", "above": ["trained *"]}
    claims.write_text(yaml.safe_dump({"map10": [entry | {"below": ["greedy (heuristic)"]}]}))
    out = tmp_path / "report"
    assert report_main([str(evals), "--out", str(out), "--claims", str(claims)]) == 0
    (row,) = [line.split("|")[1:-1] for line in (out / "claims.md").read_text().splitlines()[2:]]
    assert "on the same fixed episodes: trained qmix 51.00 ± 1.41 (2)" in row[4]
    assert row[2].strip().startswith("**yes**: significantly higher after Holm: trained qmix (Holm p = ")

    entry["above"] = ["trained vdn*"]  # matches nothing: the pattern is reported as not run
    claims.write_text(yaml.safe_dump({"map10": [entry | {"below": ["greedy (heuristic)"]}]}))
    assert report_main([str(evals), "--out", str(out), "--claims", str(claims)]) == 0
    assert "**not run**: no runs of trained vdn*" in (out / "claims.md").read_text()


def test_a_claim_names_a_method_by_one_setting_beside_two_sweeps_of_it(tmp_path: Path) -> None:
    """Figure 7's claims name ``cnn_semu``; table 4's delta sweep and figure 10's lambda sweep of it in the
    same report label its runs by both settings; a claim still names each by the one it is about
    (``cnn_semu delta=0.13``, ``cnn_semu lambda=0.5``), the others at their defaults, and ``cnn_semu``
    alone is the run at every default. Before the sweeps have run, ``cnn_semu lambda=0.1`` is figure 7's
    CNN-SEMU, at that lambda."""
    base, sweeps = tmp_path / "base", tmp_path / "sweeps"
    points = {"default": (1.3e-3, 0.1, 60.0), "delta": (1.3e-1, 0.1, 20.0), "lambda": (1.3e-3, 0.5, 40.0)}
    for seed in range(3):
        make_run(base, f"qmix_{seed}", seed=seed, steps=STEPS, reward=[0.0] * 9 + [50.0 + seed] * 2)
        for name, (delta, weight, reward) in points.items():
            make_run(
                base if name == "default" else sweeps, f"cnn_semu_{name}_{seed}", algo="cnn_semu", seed=seed,
                steps=STEPS, reward=[0.0] * 9 + [reward + seed] * 2, algo__memory__enabled=True,
                algo__memory__delta=delta, algo__memory_weight=weight,
            )  # fmt: skip
    claims = tmp_path / "claims.yaml"
    common = {"source": "fig. 7a", "paper": "-", "metric": "episode_reward"}
    entries = [
        {**common, "claim": "cnn_semu beats qmix", "above": ["cnn_semu"], "below": ["qmix"]},
        {**common, "claim": "100x delta beats qmix", "above": ["cnn_semu delta=0.13"], "below": ["qmix"]},
        {
            **common,
            "claim": "0.1 beats 0.5",
            "above": ["cnn_semu lambda=0.1"],
            "below": ["cnn_semu lambda=0.5"],
        },
    ]
    claims.write_text(yaml.safe_dump({"map10": entries}))

    def judged(*paths: Path) -> list[list[str]]:
        out = tmp_path / "report"
        assert report_main([*map(str, paths), "--out", str(out), "--claims", str(claims)]) == 0
        return [line.split("|")[1:-1] for line in (out / "claims.md").read_text().splitlines()[2:]]

    rows = judged(base)
    assert rows[0][2].strip().startswith("**reproduced**") and "cnn_semu 61.00 ± 1.00 (3)" in rows[0][4]
    assert rows[1][2].strip() == "**not run**: no runs of cnn_semu delta=0.13"
    assert rows[2][2].strip() == "**not run**: no runs of cnn_semu lambda=0.5"
    assert "cnn_semu 61.00 ± 1.00 (3)" in rows[2][4]

    rows = judged(base, sweeps)
    verdicts = {r[1].strip(): r[2].strip() for r in rows}
    assert verdicts["cnn_semu beats qmix"].startswith("**reproduced**"), verdicts
    assert "cnn_semu delta=0.0013 lambda=0.1 61.00 ± 1.00 (3)" in rows[0][4]
    assert verdicts["100x delta beats qmix"].startswith("**not reproduced**"), verdicts
    assert "cnn_semu delta=0.13 lambda=0.1 21.00 ± 1.00 (3)" in rows[1][4]
    assert verdicts["0.1 beats 0.5"].startswith("**reproduced**"), verdicts
    assert "cnn_semu delta=0.0013 lambda=0.5 41.00 ± 1.00 (3)" in rows[2][4]


# ------------------------------------------------------------------ Holm, effect sizes, bootstrap, verdicts
def test_holm_matches_a_hand_computed_example() -> None:
    """Sorted 0.005, 0.01, 0.03, 0.04 of m = 4 tests: times 4, 3, 2, 1 is 0.02, 0.03, 0.06, 0.04; the last
    is raised to the one before it (step-down), each capped at 1."""
    assert holm([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    assert holm([0.5, 0.6]).tolist() == [1.0, 1.0]
    assert holm([0.02]).tolist() == [0.02]  # one test: nothing to correct
    assert holm([]).tolist() == []


def test_holm_matches_statsmodels() -> None:
    multipletests = pytest.importorskip("statsmodels.stats.multitest").multipletests
    p = np.random.default_rng(3).uniform(0, 0.2, size=9)
    assert holm(p) == pytest.approx(multipletests(p, method="holm")[1])


def test_hedges_g_uses_the_exact_small_sample_correction() -> None:
    assert hedges_correction(2) == pytest.approx(1 / np.sqrt(np.pi))  # Γ(1) / (1 · Γ(1/2))
    assert hedges_correction(4) == pytest.approx(1 / (np.sqrt(2) * np.sqrt(np.pi) / 2))  # Γ(2)/(√2 Γ(3/2))
    assert hedges_correction(200) == pytest.approx(1 - 3 / (4 * 200 - 1), abs=1e-5)
    assert np.isnan(hedges_correction(1))
    # pooled sd 1, d = -3 on 4 degrees of freedom
    assert hedges_g(np.array([1.0, 2, 3]), np.array([4.0, 5, 6])) == pytest.approx(-3 * hedges_correction(4))
    # one-sample: (mean - c) / sd on n - 1 degrees of freedom
    assert hedges_g(np.array([1.0, 2, 3]), c=0.0) == pytest.approx(2 * hedges_correction(2))
    assert np.isnan(hedges_g(np.array([2.0, 2, 2]), c=0.0))  # no spread: no standardized effect


def test_bootstrap_interval_is_deterministic_and_covers_a_known_difference() -> None:
    a, b = np.array([10.0, 11, 13]), np.array([1.0, 2, 4])
    assert bootstrap_ci(a, b) == bootstrap_ci(a, b)  # the fixed seed: same numbers, same interval
    wide = np.random.default_rng(1).normal(size=8)
    assert bootstrap_ci(wide, c=0.0) != bootstrap_ci(wide, c=0.0, seed=BOOTSTRAP_SEED + 1)  # the seed counts
    lo, hi = bootstrap_ci(a, b)
    assert lo <= a.mean() - b.mean() <= hi and lo >= 6 and hi <= 12  # within the resamples' extremes
    assert bootstrap_ci(np.full(3, 5.0), np.full(4, 2.0)) == (3.0, 3.0)  # no spread: the difference itself
    assert bootstrap_ci(np.full(3, 5.0), c=1.5) == (3.5, 3.5)

    # coverage: normal samples whose means differ by 1; the 95 % interval holds it about 95 % of the time
    rng = np.random.default_rng(7)
    hits = [
        lo <= 1.0 <= hi
        for lo, hi in (
            bootstrap_ci(rng.normal(1.0, 1.0, 40), rng.normal(0.0, 1.0, 40), resamples=2000)
            for _ in range(300)
        )
    ]
    assert 0.9 <= np.mean(hits) <= 0.99


def test_a_claim_needs_its_direction_to_survive_holm() -> None:
    """Two comparisons each at p about 0.037 (Welch, 3 seeds against 3): significant alone, not after Holm
    (0.075): not shown, whichever way they point. Reversed beyond the correction: not reproduced."""
    a, b, c = samples("a", 10, 11, 12), samples("b", 7.5, 8.5, 9.5), samples("c", 7.5, 8.5, 9.5)
    assert compare(a, b, "higher") == ("holds", pytest.approx(0.0375, abs=1e-3))  # one test alone
    two = claim(below=("b", "c"))
    result = verdict(two, {"a": a, "b": b, "c": c})
    assert result.word == "not shown" and "Holm p = 0.07" in result.why
    assert [t.p_holm for t in result.comparisons] == pytest.approx([0.075, 0.075], abs=2e-3)
    reversed_weakly = verdict(claim(below=("b", "c"), better="lower"), {"a": a, "b": b, "c": c})
    assert reversed_weakly.word == "not shown"  # significantly the other way alone, not after Holm

    strong = {"a": samples("a", 1, 2, 3), "b": samples("b", 10, 11, 12), "c": samples("c", 30, 31, 33)}
    flipped = verdict(two, strong)  # a far below both: the reversal survives Holm
    assert (
        flipped.word == "not reproduced" and "b significantly higher than a (Holm p < 0.001)" in flipped.why
    )
    assert verdict(claim(below=("b",)), {"a": samples("a", 1, 5, 9), "b": samples("b", 2, 4, 6)}).word == (
        "not shown"
    )
    won = verdict(
        two, {"a": samples("a", 30, 31, 33), "b": samples("b", 1, 2, 3), "c": samples("c", 10, 11, 12)}
    )
    assert won.word == "reproduced" and won.why.startswith("every comparison significant after Holm")
    (row,) = [t for t in won.comparisons if t.below == "b"]
    assert row.diff == pytest.approx(31.333 - 2, abs=1e-3) and row.test == "welch"
    assert row.p_holm == pytest.approx(2 * row.p)  # the smaller of two p-values, times 2
    assert row.ci == bootstrap_ci(np.array([30.0, 31, 33]), np.array([1.0, 2, 3]))
