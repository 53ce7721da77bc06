"""One pairwise comparison of a claim (:mod:`mcrs_lab.analysis.claims`): its test, effect size and
interval, and Holm's correction over a claim's comparisons.

The test of a pair:

- two learners (or trained policies): Welch's t-test over their seeds;
- a learner against a heuristic that played the same episodes (the learner's periodic evaluation during
  training uses ``train.eval_seed`` and ``train.eval_episodes``; ``mcrs-eval`` at that seed and number of
  episodes on the same env config plays the same layouts): the heuristic's score on those episodes is one
  number, not a sample (a deterministic heuristic scores it every time; the random heuristic's own draws
  follow the same seed), so the learner's seeds are tested against it with the one-sample t-test, which
  pairs every seed with the heuristic on the same layouts (for trained policies evaluated with
  ``mcrs-eval``, the heuristic's mean over the same evaluation seeds);
- a learner against a heuristic evaluated on other episodes (other evaluation seeds, another task): Welch's
  t-test over the learner's training seeds and the heuristic's evaluation seeds, as unpaired samples; the
  table says the heuristic did not play the learners' episodes.

Each comparison shows the difference of means (above minus below, in the metric's units), Hedges' g (the
difference over the pooled standard deviation, or over the learner's for the one-sample test, times the
exact small-sample correction J(df)) and a 95 % percentile bootstrap interval of the difference
(``BOOTSTRAP_RESAMPLES`` resamples of the seeds within each group, generator seeded with
``BOOTSTRAP_SEED``: the same records give the same interval). With three seeds a group has ten distinct
resampled means: the interval is a description of the spread, narrower than a t interval, and the verdict
rests on the tests.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import special, stats

from mcrs_lab.analysis.evaluations import Layout

ALPHA = 0.05  # the family-wise error rate of a claim's two-sided tests (Holm)
BOOTSTRAP_RESAMPLES = 10_000  # resamples of the seeds for a difference's confidence interval
BOOTSTRAP_SEED = 0  # the bootstrap's generator: the same numbers give the same interval
CONFIDENCE = 0.95  # the bootstrap interval's level


@dataclass(frozen=True)
class Samples:
    """One method's numbers: one per training seed (or evaluation seed, for a heuristic).

    ``layouts``: the episodes every number was evaluated on (empty: unknown). ``on_layouts``: a
    heuristic's score on each layout it played, which a learner on the same episodes is tested against."""

    label: str
    values: np.ndarray
    complete: bool = True  # False: the method's runs stop before the window ends
    layouts: frozenset[Layout] = frozenset()
    on_layouts: tuple[tuple[Layout, float], ...] = ()
    heuristic: bool = False

    @property
    def mean(self) -> float:
        return float(self.values.mean())

    @property
    def std(self) -> float:
        return float(self.values.std(ddof=1)) if len(self.values) > 1 else float("nan")

    def text(self) -> str:
        spread = f" ± {self.std:.2f}" if len(self.values) > 1 else ""
        return f"{self.label} {self.mean:.2f}{spread} ({len(self.values)})"


@dataclass(frozen=True)
class Comparison:
    """One pairwise test of a claim: does ``above`` beat ``below`` on the claim's metric?"""

    above: str
    below: str
    better: str  # higher | lower: the claimed direction of ``diff``
    test: str  # welch | one-sample (against a heuristic's score on the same episodes) | paired | none (one number)
    diff: float  # mean of above minus mean of below (the heuristic's score on the learner's episodes)
    g: float  # Hedges' g of diff (NaN where it is not defined)
    ci: tuple[float, float]  # the bootstrap interval of diff
    p: float  # the test's two-sided p-value (NaN: not tested)
    p_holm: float = float("nan")  # p adjusted over the claim's tests (Holm)
    other_episodes: bool = False  # a heuristic that did not play the learner's episodes
    score: float = float("nan")  # one-sample: the heuristic's score on the learner's episodes

    @property
    def outcome(self) -> str:
        """``holds`` / ``reversed`` (significant after Holm, where it was applied, either way), ``noise``,
        or ``few`` (a side with fewer than two numbers: no test)."""
        if not np.isfinite(self.p):
            return "few"
        p = self.p_holm if np.isfinite(self.p_holm) else self.p
        if p < ALPHA:
            return "holds" if (self.diff > 0) == (self.better == "higher") else "reversed"
        return "noise"

    def text(self) -> str:
        """``a vs b: Δ +1.03 [-2.45, +4.30], g +0.31, p 0.659 → 1.000`` (p before → after Holm; how it was
        tested where that is not Welch's test, and a heuristic that played other episodes)."""
        if self.test == "none":
            return f"{self.above} vs {self.below}: Δ {_signed(self.diff)[0]}, one number on a side: no test"
        lo, hi = self.ci
        g = f"g {self.g:+.2f}" if np.isfinite(self.g) else "g -"
        holm = p_text(self.p_holm) if np.isfinite(self.p_holm) else "-"
        d, lo_text, hi_text = _signed(self.diff, lo, hi)
        tested = f"Δ {d} [{lo_text}, {hi_text}], {g}, p {p_text(self.p)} → {holm}"
        how = {"one-sample": ", one-sample on the same episodes", "paired": ", paired over seeds"}.get(
            self.test, ""
        )
        other = ", heuristic on other episodes" if self.other_episodes else ""
        return f"{self.above} vs {self.below}: {tested}{how}{other}"


def _signed(*values: float) -> tuple[str, ...]:
    """Signed numbers to three significant figures of the largest, all with its decimals."""
    largest = max((abs(v) for v in values if np.isfinite(v)), default=0.0)
    decimals = min(4, max(0, 2 - int(np.floor(np.log10(largest))))) if largest > 0 else 2
    return tuple(f"{v:+.{decimals}f}" for v in values)


def p_text(p: float) -> str:
    return "<0.001" if p < 0.001 else f"{p:.3f}"


def p_is(p: float) -> str:
    """``= 0.021`` or ``< 0.001``: a p-value after its name."""
    return "< 0.001" if p < 0.001 else f"= {p:.3f}"


def holm(pvalues: list[float] | np.ndarray) -> np.ndarray:
    """Holm's step-down adjustment: the k-th smallest of m p-values times (m - k + 1), kept from falling
    below the one before it and capped at 1. Rejecting where the adjusted p is below alpha holds the
    family-wise error rate at alpha whatever the tests' dependence."""
    p = np.asarray(pvalues, dtype=float)
    adjusted = np.empty_like(p)
    running = 0.0
    for rank, i in enumerate(np.argsort(p, kind="stable")):
        running = max(running, min(1.0, (len(p) - rank) * p[i]))
        adjusted[i] = running
    return adjusted


def hedges_correction(df: float) -> float:
    """J(df) = Γ(df/2) / (sqrt(df/2) Γ((df - 1)/2)): the exact factor that makes a standardized mean
    difference on ``df`` degrees of freedom unbiased (about 1 - 3/(4 df - 1)); NaN below 2."""
    if df < 2:
        return float("nan")
    return float(np.exp(special.gammaln(df / 2) - 0.5 * np.log(df / 2) - special.gammaln((df - 1) / 2)))


def hedges_g(a: np.ndarray, b: np.ndarray | None = None, c: float = 0.0) -> float:
    """Hedges' g of mean(a) - mean(b) over the pooled standard deviation (n_a + n_b - 2 degrees of
    freedom), or, without ``b``, of mean(a) - c over a's own (n_a - 1): NaN with no spread or too few."""
    if b is None:
        df, spread, diff = len(a) - 1, float(a.std(ddof=1)) if len(a) > 1 else 0.0, float(a.mean()) - c
    else:
        df = len(a) + len(b) - 2
        pooled = ((len(a) - 1) * a.var(ddof=1) + (len(b) - 1) * b.var(ddof=1)) / df if df > 0 else 0.0
        spread, diff = float(np.sqrt(pooled)), float(a.mean() - b.mean())
    if df < 2 or spread <= 0:
        return float("nan")
    return hedges_correction(df) * diff / spread


def bootstrap_ci(
    a: np.ndarray,
    b: np.ndarray | None = None,
    c: float = 0.0,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
    confidence: float = CONFIDENCE,
) -> tuple[float, float]:
    """The percentile bootstrap interval of mean(a) - mean(b) (or mean(a) - c): ``a`` and ``b`` are
    resampled with replacement each within itself (training seeds within their method), from a generator
    seeded with ``seed``, so the same numbers always give the same interval."""
    rng = np.random.default_rng(seed)
    means = a[rng.integers(0, len(a), (resamples, len(a)))].mean(axis=1)
    if b is not None:
        means = means - b[rng.integers(0, len(b), (resamples, len(b)))].mean(axis=1)
    else:
        means = means - c
    lo, hi = np.quantile(means, [(1 - confidence) / 2, (1 + confidence) / 2])
    return float(lo), float(hi)


def _score_on(heuristic: Samples, layouts: frozenset[Layout]) -> float | None:
    """A heuristic's score on ``layouts`` (its mean over them), or None where it did not play them all."""
    if not heuristic.heuristic or not layouts:
        return None
    scores = dict(heuristic.on_layouts)
    if not all(layout in scores for layout in layouts):
        return None
    return float(np.mean([scores[layout] for layout in sorted(layouts)]))


def pairwise_test(a: Samples, b: Samples, better: str) -> Comparison:
    """``a`` against ``b`` (module docstring): the one-sample test of a learner's seeds against a heuristic's
    score on the same episodes, else Welch's test; the difference, Hedges' g and the bootstrap interval."""
    for learner, heuristic, sign in ((a, b, 1.0), (b, a, -1.0)):
        score = None if learner.heuristic else _score_on(heuristic, learner.layouts)
        if score is None:
            continue
        x = learner.values
        diff = sign * (float(x.mean()) - score) if len(x) else float("nan")
        if len(x) < 2:
            ci = (diff, diff)
            return Comparison(
                a.label, b.label, better, "none", diff, float("nan"), ci, float("nan"), score=score
            )
        lo, hi = bootstrap_ci(x, c=score)
        ci = (lo, hi) if sign > 0 else (-hi, -lo)
        p = _one_sample_p(x, score)
        g = sign * hedges_g(x, c=score)
        return Comparison(a.label, b.label, better, "one-sample", diff, g, ci, p, score=score)

    other = a.heuristic != b.heuristic
    diff = float(a.values.mean() - b.values.mean()) if len(a.values) and len(b.values) else float("nan")
    if len(a.values) < 2 or len(b.values) < 2:
        ci = (diff, diff)
        return Comparison(
            a.label, b.label, better, "none", diff, float("nan"), ci, float("nan"), other_episodes=other
        )
    a_fixed, b_fixed = _no_spread(a.values), _no_spread(b.values)
    if a_fixed and b_fixed:  # no spread at all: the t-test is undefined
        p = 0.0 if diff != 0 else 1.0
    elif a_fixed or b_fixed:  # Welch's test against a constant is the one-sample test against it
        varied, fixed = (b.values, a.values) if a_fixed else (a.values, b.values)
        p = _one_sample_p(varied, float(fixed.mean()))
    else:
        p = float(stats.ttest_ind(a.values, b.values, equal_var=False).pvalue)
    g, ci = hedges_g(a.values, b.values), bootstrap_ci(a.values, b.values)
    return Comparison(a.label, b.label, better, "welch", diff, g, ci, p, other_episodes=other)


def paired_test(above: str, below: str, a: np.ndarray, b: np.ndarray, better: str) -> Comparison:
    """``a`` against ``b`` measured on the same units, in the same order (a trained policy's seeds evaluated
    at two settings): the t-test of the differences, their Hedges' g (over the differences' own spread) and
    the bootstrap interval of their mean."""
    d = np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)
    diff = float(d.mean()) if len(d) else float("nan")
    if len(d) < 2:
        return Comparison(above, below, better, "none", diff, float("nan"), (diff, diff), float("nan"))
    return Comparison(
        above, below, better, "paired", diff, hedges_g(d), bootstrap_ci(d), _one_sample_p(d, 0.0)
    )


def compare(a: Samples, b: Samples, better: str) -> tuple[str, float]:
    """Does ``a`` beat ``b``, one test alone (no correction)? ``holds`` / ``reversed`` (significant at
    ``ALPHA`` either way), ``noise``, or ``few`` (fewer than two numbers on a side); and the p-value (NaN
    when not tested)."""
    result = pairwise_test(a, b, better)
    return result.outcome, result.p


def _one_sample_p(x: np.ndarray, c: float) -> float:
    """The one-sample t-test's two-sided p of mean(x) = c; with no spread in ``x`` (the test is undefined),
    0 where x differs from c and 1 where it is c."""
    if _no_spread(x):
        return 0.0 if float(x.mean()) != c else 1.0
    return float(stats.ttest_1samp(x, c).pvalue)


def _no_spread(values: np.ndarray) -> bool:
    """Whether the values are equal but for float rounding (a heuristic's coverage of 0.975 on every
    evaluation seed): scipy's two-sample moments of such a sample warn of catastrophic cancellation."""
    return bool(np.ptp(values) <= 1e-9 * max(1.0, float(np.abs(values).max())))


def corrected(tests: list[Comparison]) -> list[Comparison]:
    """``tests`` with their p-values adjusted by Holm over those that were tested (one claim's family)."""
    tested = [k for k, t in enumerate(tests) if np.isfinite(t.p)]
    adjusted = holm([tests[k].p for k in tested])
    out = list(tests)
    for k, p in zip(tested, adjusted, strict=True):
        out[k] = replace(tests[k], p_holm=float(p))
    return out
