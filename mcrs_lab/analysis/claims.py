"""The paper's claims checked on our runs: ``claims.md`` of ``mcrs-report``.

A claim (``paper_claims.yaml``, per map) says that some methods beat others on one evaluation metric,
early or late in training. Each training seed gives one number, its mean evaluation over the window (the
last tenth of the budget, or its first third): the mean over a window is steadier than the last
evaluation alone. A heuristic gives one number per evaluation seed. Two methods are compared with Welch's
t-test over those numbers: a difference counts only when it is significant at ``ALPHA`` (two-sided), so
three seeds that overlap decide nothing, and one seed never decides.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path

import numpy as np
import yaml
from scipy import stats

from mcrs.experiment.util.tables import markdown
from mcrs.experiment.util.untrusted import UntrustedInput, check_yaml_text, read_yaml_text
from mcrs.viz.learning_curves import Curve
from mcrs_lab.analysis.evaluations import heuristic_samples, trained_samples
from mcrs_lab.analysis.runs import EvaluationRow

ALPHA = 0.05  # significance of Welch's two-sided t-test
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
    """One method's numbers: one per training seed (or evaluation seed, for a heuristic)."""

    label: str
    values: np.ndarray
    complete: bool = True  # False: the method's runs stop before the window ends

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
) -> tuple[Claim, dict[str, Samples]]:
    """The claim with its label patterns (``trained *``) replaced by the methods they match, and the
    numbers of every method it names that the report has: training runs (per seed, over the window),
    heuristics (per evaluation seed) and trained policies evaluated on fixed episodes (per trained run:
    their final checkpoints, so every window is theirs)."""
    found: dict[str, Samples] = {}
    for label, curve in curves.get(claim.metric, {}).items():
        found[label] = window_samples(curve, claim.window, budget)
    for label, values in heuristic_samples(evaluations, comm_range, claim.metric).items():
        found[label] = Samples(label, values)
    for label, values in trained_samples(evaluations, claim.metric).items():
        found.setdefault(label, Samples(label, values))
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
def compare(a: Samples, b: Samples, better: str) -> tuple[str, float]:
    """Does ``a`` beat ``b``? ``holds`` / ``reversed`` (significant either way), ``noise``, or ``few``
    (fewer than two numbers on a side); and the p-value (NaN when not tested)."""
    if len(a.values) < 2 or len(b.values) < 2:
        return "few", float("nan")
    diff = a.mean - b.mean
    if better == "lower":
        diff = -diff
    a_fixed, b_fixed = _no_spread(a.values), _no_spread(b.values)
    if a_fixed and b_fixed:  # no spread at all: the t-test is undefined
        p = 0.0 if diff != 0 else 1.0
    elif a_fixed or b_fixed:  # Welch's test against a constant is the one-sample test against it
        varied, fixed = (b.values, a.values) if a_fixed else (a.values, b.values)
        p = float(stats.ttest_1samp(varied, fixed.mean()).pvalue)
    else:
        p = float(stats.ttest_ind(a.values, b.values, equal_var=False).pvalue)
    if p < ALPHA:
        return ("holds" if diff > 0 else "reversed"), p
    return "noise", p


def _no_spread(values: np.ndarray) -> bool:
    """Whether the values are equal but for float rounding (a heuristic's coverage of 0.975 on every
    evaluation seed): scipy's two-sample moments of such a sample warn of catastrophic cancellation."""
    return bool(np.ptp(values) <= 1e-9 * max(1.0, float(np.abs(values).max())))


def verdict(claim: Claim, samples: dict[str, Samples]) -> Verdict:
    """``claim`` judged on ``samples``: reproduced (every comparison it needs is significant its way), not
    reproduced (significantly the other way), not shown (within noise, or one seed), or not run."""
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

    rivals = [samples[m] for m in claim.below]
    outcomes = {m: [(r.label, *compare(samples[m], r, claim.better)) for r in rivals] for m in candidates}
    state = {m: _state([o for _, o, _ in results]) for m, results in outcomes.items()}
    single = [s.label for s in compared if len(s.values) < 2]
    if claim.quantifier == "all":
        if all(v == "holds" for v in state.values()):
            worst = max(p for results in outcomes.values() for _, _, p in results)
            return Verdict("reproduced", f"every comparison significant (largest p = {worst:.3f})", compared)
        for m, results in outcomes.items():
            for r, o, p in results:
                if o == "reversed":
                    return Verdict(
                        "not reproduced", f"{r} significantly {claim.better} than {m} (p = {p:.3f})", compared
                    )
        if single:
            return Verdict("not shown", f"one seed of {', '.join(single)}: no test", compared)
        m, r, p = max(
            ((m, r, p) for m, res in outcomes.items() for r, o, p in res if o == "noise"), key=lambda x: x[2]
        )
        return Verdict("not shown", f"{m} against {r} within noise (p = {p:.2f})", compared)

    later = f"; {unfinished}" if unfinished else ""
    winners = [m for m, v in state.items() if v == "holds"]
    if winners:
        won = ", ".join(f"{m} (p = {max(p for _, _, p in outcomes[m]):.3f})" for m in winners)
        return Verdict("reproduced", f"significantly {claim.better}: {won}{later}", compared)
    summary = "; ".join(_summary(m, outcomes[m], state[m]) for m in candidates)
    # "no method does" needs every method of the claim finished: one still running might
    every_one_worse = all(v == "reversed" for v in state.values()) and not unfinished
    word = "not reproduced" if every_one_worse else "not shown"
    return Verdict(word, f"{summary}{later}", compared)


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
    return (
        f"{method}: {'significantly the other way' if state == 'reversed' else 'within noise'} (p = {p:.3f})"
    )


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
) -> str:
    """Markdown: source, claim, the paper's numbers, ours (mean ± std (seeds) per method over the
    window, or ``window_text`` where there is none: evaluations of final checkpoints), and the verdict
    with its reason. ``aliases`` (:func:`~mcrs_lab.analysis.runs.default_labels`): a plain algorithm name the
    report has no method of stands for its label at the default settings."""
    rows = []
    for claim in claims:
        claim, samples = method_samples(claim, curves, evaluations, comm_range, budget, aliases)
        result = verdict(claim, samples)
        word = OUR_WORDS.get(result.word, result.word) if claim.ours else result.word
        ours = "; ".join(s.text() for s in result.compared) or "-"
        metric = METRIC_TEXT.get(claim.metric, claim.metric.replace("_", " "))
        what = f"{metric}, {window_text or WINDOW_TEXT[claim.window]}"
        rows.append([claim.source, claim.claim, claim.paper, f"{what}: {ours}", f"**{word}**: {result.why}"])
    return markdown(["source", "claim", "paper", "ours (mean ± std (seeds))", "verdict"], rows, left=5)
