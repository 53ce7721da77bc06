"""The paper's claims checked on our runs: ``claims.md`` of ``mcrs-report``.

A claim (``paper_claims.yaml``, per map) says that some methods beat others on one evaluation metric,
early or late in training. Each training seed gives one number, its mean evaluation over the window (the
last tenth of the budget, or its first third): the mean over a window is steadier than the last
evaluation alone. A claim needs several pairwise comparisons (each method of ``above`` against each of
``below``); each is a two-sided test, and Holm's step-down correction holds the claim's family of tests at
``ALPHA``. A verdict says "reproduced" only where the claimed direction survives the correction, "not
reproduced" only where the reversed direction does, and "not shown" otherwise: three seeds that overlap
decide nothing, and one seed never decides.

How each pair is tested, and what each comparison shows, is :mod:`mcrs_lab.analysis.pairwise`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path

import numpy as np
import yaml

from mcrs.experiment.util.tables import markdown
from mcrs.experiment.util.untrusted import UntrustedInput, check_yaml_text, read_yaml_text
from mcrs.viz.learning_curves import Curve
from mcrs_lab.analysis.evaluations import (
    Layout,
    heuristic_layout_values,
    heuristic_samples,
    trained_layouts,
    trained_samples,
)
from mcrs_lab.analysis.pairwise import Comparison, Samples, corrected, p_is, pairwise_test
from mcrs_lab.analysis.runs import EvaluationRow

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
                f"every comparison significant after Holm (largest Holm p {p_is(worst)})",
                compared,
                tests,
            )
        for m, results in outcomes.items():
            for r, o, p in results:
                if o == "reversed":
                    why = f"{r} significantly {claim.better} than {m} (Holm p {p_is(p)})"
                    return Verdict("not reproduced", why, compared, tests)
        if single:
            return Verdict("not shown", f"one seed of {', '.join(single)}: no test", compared, tests)
        m, r, p = max(
            ((m, r, p) for m, res in outcomes.items() for r, o, p in res if o == "noise"), key=lambda x: x[2]
        )
        return Verdict("not shown", f"{m} against {r} within noise (Holm p {p_is(p)})", compared, tests)

    later = f"; {unfinished}" if unfinished else ""
    winners = [m for m, v in state.items() if v == "holds"]
    if winners:
        won = ", ".join(f"{m} (Holm p {p_is(max(p for _, _, p in outcomes[m]))})" for m in winners)
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
    return f"{method}: {way} (Holm p {p_is(p)})"


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
        row = [claim.source, claim.claim, f"**{word}**: {result.why}", claim.paper, f"{what}: {ours}", tests]
        rows.append(row)  # the verdict beside the claim, the evidence after it
    header = ["source", "claim", "verdict", "paper", "ours (mean ± std (seeds))", COMPARISONS_HEADER]
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
    if not mine:  # no learner's seeds to set it beside: its numbers alone
        return samples.text()
    scores = sorted({t.score for t in mine if np.isfinite(t.score)})
    parts = (
        [f"{samples.label} {', '.join(f'{v:.2f}' for v in scores)} on the learners' episodes"]
        if scores
        else []
    )
    if not scores or any(t.other_episodes for t in mine):
        parts.append(f"{samples.text()} over evaluation seeds, not the learners' episodes")
    return "; ".join(parts)
