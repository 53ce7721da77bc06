"""Evaluations on fixed episodes (``mcrs-eval`` runs and their records) as report rows: the heuristics
(each evaluation seed one sample) and trained policies (each trained run one sample), and the heuristics as
the horizontal reference lines of the learning curves.

A :data:`Layout` names the episodes a number comes from: the task played (the env config), the evaluation
seed and the number of episodes. Two evaluations with the same layout played the same episodes: a
learner's periodic evaluation during training (``train.eval_seed``, ``train.eval_episodes``) and
``mcrs-eval seed=<train.eval_seed> episodes=<train.eval_episodes>`` on the same env config reset to the same
maps, targets and start positions."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path
from typing import Any

import numpy as np

from mcrs.env.config import EnvConfig, with_legacy_values
from mcrs.viz.learning_curves import CURVE_METRICS, FINAL_METRICS, Reference, confidence_half_width
from mcrs_lab.analysis.runs import EvaluationRow

HEURISTIC_ORDER = ("random", "lawnmower", "greedy", "coverage")
#: (the task as canonical JSON, evaluation seed, episodes): the episodes an evaluation played.
Layout = tuple[str, int, int]
#: Env fields that change neither the episodes nor their scores: runtime fields, pictures, a policy's
#: wider view of its own map (what an agent reads: ``mcrs.policies.policy_env``).
NOT_THE_TASK = ("num_envs", "device", "expose_beliefs", "invalid_action", "far_view")


def task_key(env: Any) -> str | None:
    """The task an env config describes, as canonical JSON: the fields it predates take the values it was
    made under, fields added since take today's defaults, numbers compare as floats. None: no env config."""
    if not isinstance(env, dict) or "name" not in env:
        return None
    defaults = {
        f.name: f.default for f in dataclasses.fields(EnvConfig) if f.default is not dataclasses.MISSING
    }
    full = {**defaults, **with_legacy_values(env)[0]}
    plain = {
        k: float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else v
        for k, v in full.items()
        if k not in NOT_THE_TASK
    }
    return json.dumps(plain, sort_keys=True, default=str)


def evaluation_layout(row: EvaluationRow) -> Layout | None:
    """The episodes an ``mcrs-eval`` row played; None where its env config is unknown."""
    key = task_key(row.env)
    return None if key is None else (key, int(row.seed), int(row.episodes))


def training_layout(config: dict[str, Any]) -> Layout | None:
    """The episodes a training run's periodic evaluations play (its env, ``train.eval_seed`` and
    ``train.eval_episodes``); None where its config lacks one of them."""
    train = config.get("train")
    key = task_key(config.get("env"))
    if key is None or not isinstance(train, dict) or "eval_seed" not in train or "eval_episodes" not in train:
        return None
    return (key, int(train["eval_seed"]), int(train["eval_episodes"]))


def _heuristics(evaluations: list[EvaluationRow], comm_range: float | None) -> dict[str, list[EvaluationRow]]:
    """The heuristics' evaluations at the training runs' R_c (any R_c when None), per policy, in order."""
    by_policy: dict[str, list[EvaluationRow]] = {}
    for row in evaluations:
        if row.is_heuristic and (comm_range is None or row.comm_range == comm_range):
            by_policy.setdefault(row.policy, []).append(row)
    names = sorted(by_policy, key=lambda p: (HEURISTIC_ORDER.index(p) if p in HEURISTIC_ORDER else 9, p))
    return {name: by_policy[name] for name in names}


def heuristic_samples(
    evaluations: list[EvaluationRow], comm_range: float | None, name: str
) -> dict[str, np.ndarray]:
    """Per heuristic (``greedy (heuristic)``), its evaluation seeds' means of metric ``name``
    (``episode_reward``): the samples its mean and spread are taken over."""
    return {
        f"{policy} (heuristic)": np.array([g.means[name] for g in group if name in g.means])
        for policy, group in _heuristics(evaluations, comm_range).items()
    }


def heuristic_layout_values(
    evaluations: list[EvaluationRow], comm_range: float | None, name: str
) -> dict[str, tuple[tuple[Layout, float], ...]]:
    """Per heuristic (``greedy (heuristic)``), its mean of metric ``name`` on each layout it played (rows
    whose env config is unknown are left out): what a learner on the same episodes is compared with."""
    out = {}
    for policy, group in _heuristics(evaluations, comm_range).items():
        pairs = [(evaluation_layout(g), g.means[name]) for g in group if name in g.means]
        out[f"{policy} (heuristic)"] = tuple((lay, v) for lay, v in pairs if lay is not None)
    return out


def heuristic_rows(evaluations: list[EvaluationRow], comm_range: float | None) -> list[dict[str, object]]:
    """The heuristics at the training runs' R_c: mean and std over evaluation seeds of each seed's mean."""
    rows = []
    names = [metric.split("/")[-1] for metric in FINAL_METRICS]
    samples = {name: heuristic_samples(evaluations, comm_range, name) for name in names}
    for policy, group in _heuristics(evaluations, comm_range).items():
        row: dict[str, object] = {"method": f"{policy} (heuristic)", "seeds": len(group), "env_steps": 0}
        for name in names:
            values = samples[name][f"{policy} (heuristic)"]
            row[f"{name}_mean"] = float(values.mean()) if len(values) else float("nan")
            row[f"{name}_std"] = float(values.std(ddof=1)) if len(values) > 1 else 0.0
        rows.append(row)
    return rows


def _trained_groups(evaluations: list[EvaluationRow]) -> dict[str, dict[str, list[EvaluationRow]]]:
    """Evaluations of trained policies: method -> trained run -> its rows (one per evaluation seed). A
    method is the policy's label (``trained qmix``), plus the run without its seed (``[shields_view/
    map20_qmix_gamma0.5]``; records made before the run's experiment was kept: ``[qmix_shield]``) where
    runs of one label differ in more than their seed."""
    by_label: dict[str, dict[str, list[EvaluationRow]]] = {}
    for row in evaluations:
        if not row.is_heuristic:
            by_label.setdefault(row.label or f"trained {_run_stem(row)}", {}).setdefault(
                row.policy, []
            ).append(row)
    methods: dict[str, dict[str, list[EvaluationRow]]] = {}
    for label in sorted(by_label):
        stems = {policy: _run_stem(rows[0]) for policy, rows in by_label[label].items()}
        for policy, rows in by_label[label].items():
            method = f"{label} [{stems[policy]}]" if len(set(stems.values())) > 1 else label
            methods.setdefault(method, {})[policy] = rows
    return dict(sorted(methods.items()))


def _run_stem(row: EvaluationRow) -> str:
    """A trained run without its seed: ``shields_view/map20_qmix_gamma0.5_seed2`` ->
    ``shields_view/map20_qmix_gamma0.5``; for a record without the run, its folder's name
    (``outputs/shield/qmix_shield_seed2`` -> ``qmix_shield``)."""
    path = Path(row.policy)
    name = row.run or (path.parent.name if path.suffix == ".pt" else path.name)
    return re.sub(r"_?seed\d+$", "", name) or name


def trained_samples(evaluations: list[EvaluationRow], name: str) -> dict[str, np.ndarray]:
    """Per trained method (``trained qmix``), each of its runs' mean of metric ``name`` over its
    evaluation seeds: the samples its mean and spread are taken over."""
    out = {}
    for method, runs in _trained_groups(evaluations).items():
        per_run = [[g.means[name] for g in group if name in g.means] for group in runs.values()]
        out[method] = np.array([np.mean(v) for v in per_run if v and np.isfinite(np.mean(v))])
    return out


def trained_layouts(evaluations: list[EvaluationRow]) -> dict[str, frozenset[Layout]]:
    """Per trained method, the layouts every one of its runs was evaluated on; empty where a run's env
    config is unknown or its runs played different episodes."""
    out: dict[str, frozenset[Layout]] = {}
    for method, runs in _trained_groups(evaluations).items():
        sets = {frozenset(evaluation_layout(g) for g in group) for group in runs.values()}
        only = sets.pop() if len(sets) == 1 else frozenset()
        out[method] = frozenset() if None in only else only
    return out


def trained_rows(evaluations: list[EvaluationRow]) -> list[dict[str, object]]:
    """Trained policies on fixed evaluation episodes: each run counts by its mean over its evaluation seeds;
    mean and std over the runs (training seeds)."""
    rows = []
    names = [metric.split("/")[-1] for metric in FINAL_METRICS]
    samples = {name: trained_samples(evaluations, name) for name in names}
    for method, runs in _trained_groups(evaluations).items():
        row: dict[str, object] = {"method": method, "seeds": len(runs), "env_steps": 0}
        for name in names:
            values = samples[name][method]
            row[f"{name}_mean"] = float(values.mean()) if len(values) else float("nan")
            row[f"{name}_std"] = float(values.std(ddof=1)) if len(values) > 1 else 0.0
        rows.append(row)
    return rows


def heuristic_references(
    evaluations: list[EvaluationRow], comm_range: float | None
) -> dict[str, list[Reference]]:
    """Per learning-curve panel, each heuristic's mean over evaluation seeds and its 95 % band: the
    horizontal lines a learner has to beat."""
    out: dict[str, list[Reference]] = {}
    for policy, group in _heuristics(evaluations, comm_range).items():
        for metric, panel in CURVE_METRICS.items():
            name = metric.split("/")[-1]
            values = np.array([g.means[name] for g in group if name in g.means])
            if len(values):
                half = float(confidence_half_width(values[:, None])[0])
                out.setdefault(panel, []).append(
                    Reference(
                        f"{policy} (heuristic)",
                        float(values.mean()),
                        half,
                        len(values),
                        "evaluation seeds" if len(values) > 1 else "evaluation seed",
                    )
                )
    return out
