"""The paper's claims checked on our runs: ``claims.md`` of ``mcrs-report``.

A claim (``paper_claims.yaml``, per map) says that some methods beat others on one evaluation metric,
early or late in training. Each training seed gives one number, its mean evaluation over the window (the
last tenth of the budget, or its first third): the mean over a window is steadier than the last
evaluation alone. A claim needs several pairwise comparisons (each method of ``above`` against each of
``below``); each is a two-sided test, and Holm's step-down correction holds the claim's family of tests at
``ALPHA``. A verdict says "reproduced" only where the claimed direction survives the correction, "not
reproduced" only where the reversed direction does, and "not shown" otherwise: three seeds that overlap
decide nothing, and one seed never decides.

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

import re
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path

import numpy as np
import yaml
from scipy import special, stats

from mcrs.experiment.tables import markdown
from mcrs.experiment.untrusted import UntrustedInput, check_yaml_text, read_yaml_text
from mcrs.viz.learning_curves import Curve
from mcrs_lab.analysis.evaluations import (
    Layout,
    heuristic_layout_values,
    heuristic_samples,
    trained_layouts,
    trained_samples,
)
from mcrs_lab.analysis.runs import EvaluationRow

ALPHA = 0.05  # the family-wise error rate of a claim's two-sided tests (Holm)
BOOTSTRAP_RESAMPLES = 10_000  # resamples of the seeds for a difference's confidence interval
BOOTSTRAP_SEED = 0  # the bootstrap's generator: the same numbers give the same interval
CONFIDENCE = 0.95  # the bootstrap interval's level
END_FRACTION = 0.1  # "end": the evaluations in the last tenth of the budget
START_FRACTION = 1 / 3  # "start": the evaluations after step 0 up to a third of the budget
WINDOWS = ("end", "start")
QUANTIFIERS = ("all", "any")
BETTER = ("higher", "lower")
FIELDS = ("claim", "source", "paper", "metric", "better", "window", "above", "below", "quantifier", "ours")
#: The metric a claim names for the mean Q_tot of replayed transitions (figure 8b; a training scalar, not
#: an evaluation metric), and how the table names each metric that is not its own words.
CLAIM_Q_TOT = "q_tot"
METRIC_TEXT = {CLAIM_Q_TOT: "mean Q_tot of replayed transitions"}


class ClaimsError(ValueError):
    """A claims file that cannot be read: names the file, the claim and the field."""


@dataclass(frozen=True)
class Claim:
    """``above`` beat ``below`` on ``metric`` (``better``: higher or lower) in ``window`` of training."""

    claim: str
    source: str
    paper: str
    metric: str
    better: str
    window: str
    above: tuple[str, ...]
    below: tuple[str, ...]
    quantifier: str = "all"
    ours: bool = False  # the project's question, not the paper's claim


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
class Verdict:
    """A claim's outcome: ``word`` (reproduced, not reproduced, not shown, not run) and why."""

    word: str
    why: str
    compared: list[Samples] = field(default_factory=list)
    comparisons: list[Comparison] = field(default_factory=list)  # its pairwise tests, Holm-adjusted


# ------------------------------------------------------------------------------------------ reading
def default_claims_path() -> Path:
    return Path(str(resources.files("mcrs_lab.analysis") / "paper_claims.yaml"))


def load_claims(path: Path, env_name: str) -> list[Claim]:
    """The claims of one map; none when the file has no entry for it. Errors name the field."""
    try:  # a document block names the file (--claims): read within the bounds of any file from outside
        text = read_yaml_text(path)
        check_yaml_text(text, str(path))
        data = yaml.safe_load(text)
    except UntrustedInput as error:
        raise ClaimsError(f"cannot read the claims file: {error}") from None
    except yaml.YAMLError as error:
        first = (str(error).strip().splitlines() or [type(error).__name__])[0]
        raise ClaimsError(f"{path}: cannot read the claims file: {first}") from None
    if not isinstance(data, dict):
        raise ClaimsError(f"{path}: expected a mapping of map name -> list of claims")
    entries = data.get(env_name) or []
    if not isinstance(entries, list):
        raise ClaimsError(f"{path}: {env_name}: expected a list of claims")
    return [_claim(path, env_name, k, entry) for k, entry in enumerate(entries)]


def _claim(path: Path, env_name: str, k: int, entry: object) -> Claim:
    where = f"{path}: {env_name}[{k}]"
    if not isinstance(entry, dict):
        raise ClaimsError(f"{where}: expected a mapping with the fields {', '.join(FIELDS)}")
    unknown = sorted(set(entry) - set(FIELDS))
    if unknown:
        raise ClaimsError(f"{where}: unknown field(s) {', '.join(unknown)}; allowed: {', '.join(FIELDS)}")
    for name in ("claim", "source", "paper", "metric", "above", "below"):
        if name not in entry:
            raise ClaimsError(f"{where}: missing field '{name}'")
    for name, allowed, default in (
        ("better", BETTER, "higher"),
        ("window", WINDOWS, "end"),
        ("quantifier", QUANTIFIERS, "all"),
    ):
        if entry.get(name, default) not in allowed:
            raise ClaimsError(f"{where}: {name}={entry[name]!r}; allowed: {', '.join(allowed)}")
    for name in ("above", "below"):
        if not isinstance(entry[name], list) or not entry[name]:
            raise ClaimsError(f"{where}: '{name}' must be a non-empty list of method labels")
    return Claim(
        claim=str(entry["claim"]),
        source=str(entry["source"]),
        paper=str(entry["paper"]),
        metric=str(entry["metric"]),
        better=entry.get("better", "higher"),
        window=entry.get("window", "end"),
        above=tuple(str(m) for m in entry["above"]),
        below=tuple(str(m) for m in entry["below"]),
        quantifier=entry.get("quantifier", "all"),
        ours=bool(entry.get("ours", False)),
    )


# ------------------------------------------------------------------------------------------ samples
def window_samples(curve: Curve, window: str, budget: int) -> Samples:
    """Per seed, the mean of its evaluations within ``window`` of a budget of ``budget`` env steps."""
    if window == "end":
        inside = curve.steps >= (1 - END_FRACTION) * budget
        complete = curve.steps[-1] >= budget
    else:
        inside = (curve.steps > 0) & (curve.steps <= START_FRACTION * budget)
        complete = curve.steps[-1] >= START_FRACTION * budget
    if not inside.any():
        return Samples(curve.label, np.array([]), complete=False)
    return Samples(curve.label, curve.values[:, inside].mean(axis=1), complete=complete)


def method_samples(
    claim: Claim,
    curves: dict[str, dict[str, Curve]],
    evaluations: list[EvaluationRow],
    comm_range: float | None,
    budget: int,
    aliases: dict[str, str] | None = None,
    layouts: dict[str, frozenset[Layout]] | None = None,
) -> tuple[Claim, dict[str, Samples]]:
    """The claim with its label patterns (``trained *``) replaced by the methods they match, and the
    numbers of every method it names that the report has: training runs (per seed, over the window; their
    evaluation episodes from ``layouts``, per label), heuristics (per evaluation seed, and their score on
    each layout) and trained policies evaluated on fixed episodes (per trained run: their final
    checkpoints, so every window is theirs)."""
    found: dict[str, Samples] = {}
    for label, curve in curves.get(claim.metric, {}).items():
        window = window_samples(curve, claim.window, budget)
        found[label] = replace(window, layouts=(layouts or {}).get(label, frozenset()))
    on_layouts = heuristic_layout_values(evaluations, comm_range, claim.metric)
    for label, values in heuristic_samples(evaluations, comm_range, claim.metric).items():
        found[label] = Samples(label, values, on_layouts=on_layouts.get(label, ()), heuristic=True)
    trained_on = trained_layouts(evaluations)
    for label, values in trained_samples(evaluations, claim.metric).items():
        found.setdefault(label, Samples(label, values, layouts=trained_on.get(label, frozenset())))
    above, below = _expand(claim.above, found, aliases or {}), _expand(claim.below, found, aliases or {})
    resolved = replace(claim, above=above, below=below)
    return resolved, {m: found[m] for m in (*above, *below) if m in found}


def _expand(labels: tuple[str, ...], found: dict[str, Samples], aliases: dict[str, str]) -> tuple[str, ...]:
    """Each label as it is (or its alias where the report has no method of that name), or, with ``*`` in it
    (any text), the methods it matches in report order (the pattern itself when none does: "no runs of")."""
    out: list[str] = []
    for label in labels:
        if "*" not in label:
            out.append(label if label in found else aliases.get(label, label))
            continue
        pattern = re.compile("^" + ".*".join(map(re.escape, label.split("*"))) + "$")
        out += [m for m in found if pattern.match(m) and m not in out] or [label]
    return tuple(out)


# ---------------------------------------------------------------------------------------- verdicts
@dataclass(frozen=True)
class Comparison:
    """One pairwise test of a claim: does ``above`` beat ``below`` on the claim's metric?"""

    above: str
    below: str
    better: str  # higher | lower: the claimed direction of ``diff``
    test: str  # welch | one-sample (against a heuristic's score on the same episodes) | none (one number)
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
        holm = _p(self.p_holm) if np.isfinite(self.p_holm) else "-"
        d, lo_text, hi_text = _signed(self.diff, lo, hi)
        tested = f"Δ {d} [{lo_text}, {hi_text}], {g}, p {_p(self.p)} → {holm}"
        how = ", one-sample on the same episodes" if self.test == "one-sample" else ""
        other = ", heuristic on other episodes" if self.other_episodes else ""
        return f"{self.above} vs {self.below}: {tested}{how}{other}"


def _signed(*values: float) -> tuple[str, ...]:
    """Signed numbers to three significant figures of the largest, all with its decimals."""
    largest = max((abs(v) for v in values if np.isfinite(v)), default=0.0)
    decimals = min(4, max(0, 2 - int(np.floor(np.log10(largest))))) if largest > 0 else 2
    return tuple(f"{v:+.{decimals}f}" for v in values)


def _p(p: float) -> str:
    return "<0.001" if p < 0.001 else f"{p:.3f}"


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


def verdict(claim: Claim, samples: dict[str, Samples]) -> Verdict:
    """``claim`` judged on ``samples`` after Holm's correction over its comparisons: reproduced (every
    comparison it needs is significant its way), not reproduced (one it needs is significantly the other
    way), not shown (within noise, or one seed), or not run."""
    names = (*claim.above, *claim.below)
    compared = [samples[m] for m in names if m in samples and len(samples[m].values)]
    absent = [m for m in names if m not in samples]
    short = [m for m in names if m in samples and not samples[m].complete]
    unfinished = ", ".join(
        [
            *([f"no runs of {', '.join(absent)}"] if absent else []),
            *(f"{m} not run to the end" for m in short),
        ]
    )
    candidates = [m for m in claim.above if m not in absent and m not in short]
    if not candidates or (claim.quantifier == "all" and unfinished) or set(claim.below) & {*absent, *short}:
        return Verdict("not run", unfinished, compared)

    tests = corrected(
        [pairwise_test(samples[m], samples[r], claim.better) for m in candidates for r in claim.below]
    )
    outcomes = {m: [(t.below, t.outcome, t.p_holm) for t in tests if t.above == m] for m in candidates}
    state = {m: _state([o for _, o, _ in results]) for m, results in outcomes.items()}
    single = [s.label for s in compared if len(s.values) < 2]
    if claim.quantifier == "all":
        if all(v == "holds" for v in state.values()):
            worst = max(p for results in outcomes.values() for _, _, p in results)
            return Verdict(
                "reproduced",
                f"every comparison significant after Holm (largest Holm p = {_p(worst)})",
                compared,
                tests,
            )
        for m, results in outcomes.items():
            for r, o, p in results:
                if o == "reversed":
                    why = f"{r} significantly {claim.better} than {m} (Holm p = {_p(p)})"
                    return Verdict("not reproduced", why, compared, tests)
        if single:
            return Verdict("not shown", f"one seed of {', '.join(single)}: no test", compared, tests)
        m, r, p = max(
            ((m, r, p) for m, res in outcomes.items() for r, o, p in res if o == "noise"), key=lambda x: x[2]
        )
        return Verdict("not shown", f"{m} against {r} within noise (Holm p = {_p(p)})", compared, tests)

    later = f"; {unfinished}" if unfinished else ""
    winners = [m for m, v in state.items() if v == "holds"]
    if winners:
        won = ", ".join(f"{m} (Holm p = {_p(max(p for _, _, p in outcomes[m]))})" for m in winners)
        return Verdict(
            "reproduced", f"significantly {claim.better} after Holm: {won}{later}", compared, tests
        )
    summary = "; ".join(_summary(m, outcomes[m], state[m]) for m in candidates)
    # "no method does" needs every method of the claim finished: one still running might
    every_one_worse = all(v == "reversed" for v in state.values()) and not unfinished
    word = "not reproduced" if every_one_worse else "not shown"
    return Verdict(word, f"{summary}{later}", compared, tests)


def _state(outcomes: list[str]) -> str:
    """One method against all its rivals: holds (against every one), reversed (by one), few, noise."""
    if all(o == "holds" for o in outcomes):
        return "holds"
    for word in ("reversed", "few"):
        if word in outcomes:
            return word
    return "noise"


def _summary(method: str, results: list[tuple[str, str, float]], state: str) -> str:
    if state == "few":
        return f"{method}: one seed"
    p = max(p for _, o, p in results if o == state) if state != "holds" else 0.0
    way = "significantly the other way" if state == "reversed" else "within noise"
    return f"{method}: {way} (Holm p = {_p(p)})"


# ------------------------------------------------------------------------------------------- table
WINDOW_TEXT = {"end": "last tenth", "start": "first third"}
OUR_WORDS = {"reproduced": "yes", "not reproduced": "no"}  # our own questions are answered, not reproduced


def claims_table(
    claims: list[Claim],
    curves: dict[str, dict[str, Curve]],
    evaluations: list[EvaluationRow],
    comm_range: float | None,
    budget: int,
    window_text: str | None = None,
    aliases: dict[str, str] | None = None,
    layouts: dict[str, frozenset[Layout]] | None = None,
) -> str:
    """Markdown: source, claim, the paper's numbers, ours (mean ± std (seeds) per method over the
    window, or ``window_text`` where there is none: evaluations of final checkpoints), each comparison
    (difference, its bootstrap interval, Hedges' g, p and Holm's p) and the verdict with its reason.
    ``aliases`` (:func:`~mcrs_lab.analysis.runs.default_labels`): a plain algorithm name the report has no
    method of stands for its label at the default settings. ``layouts``: per training label, the episodes
    its periodic evaluations played (a heuristic on them is compared one-sample)."""
    rows = []
    for claim in claims:
        claim, samples = method_samples(claim, curves, evaluations, comm_range, budget, aliases, layouts)
        result = verdict(claim, samples)
        word = OUR_WORDS.get(result.word, result.word) if claim.ours else result.word
        ours = "; ".join(_sample_text(s, result.comparisons) for s in result.compared) or "-"
        metric = METRIC_TEXT.get(claim.metric, claim.metric.replace("_", " "))
        what = f"{metric}, {window_text or WINDOW_TEXT[claim.window]}"
        tests = "<br>".join(t.text() for t in result.comparisons) or "-"
        row = [claim.source, claim.claim, claim.paper, f"{what}: {ours}", tests, f"**{word}**: {result.why}"]
        rows.append(row)
    header = ["source", "claim", "paper", "ours (mean ± std (seeds))", COMPARISONS_HEADER, "verdict"]
    return markdown(header, rows, left=6)


#: The comparisons column: each pair's difference with its 95 % bootstrap interval, Hedges' g, the raw p
#: and Holm's adjusted p over the claim's tests.
COMPARISONS_HEADER = "comparisons: Δ [95 % bootstrap CI], Hedges' g, p → Holm p"


def _sample_text(samples: Samples, tests: list[Comparison]) -> str:
    """A method's numbers; a heuristic's says whether it played the learners' episodes: its score there
    (one number), or its evaluation seeds' mean ± std where it did not."""
    if not samples.heuristic:
        return samples.text()
    mine = [t for t in tests if samples.label in (t.above, t.below)]
    scores = sorted({t.score for t in mine if np.isfinite(t.score)})
    parts = (
        [f"{samples.label} {', '.join(f'{v:.2f}' for v in scores)} on the learners' episodes"]
        if scores
        else []
    )
    if not scores or any(t.other_episodes for t in mine):
        parts.append(f"{samples.text()} over evaluation seeds, not the learners' episodes")
    return "; ".join(parts)
