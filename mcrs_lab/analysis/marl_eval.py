"""Training runs as marl-eval's raw-data JSON (instadeepai/marl-eval), the format MARL papers compare
methods with (``data_process_pipeline``, performance profiles, sample-efficiency curves)::

    {"mcrs": {"map10": {"cnn_semu": {"run_0": {"step_0": {"step_count": 0, "episode_reward": [12.3], ...},
                                               ...,
                                               "step_k": {...},
                                               "absolute_metrics": {"episode_reward": [61.2], ...}}}}}}

Environment ``mcrs``; a task per map; an algorithm per method label of the report (``cnn_semu``,
``cnn_semu lambda=0.5``; the seeds of a method are its runs, ``run_<i>`` in seed order); a step per greedy
evaluation, ``step_count`` its env steps. marl-eval's lists hold one value per evaluation episode; a run
logs the mean over its ``train.eval_episodes`` episodes, so each list holds that mean alone.
``absolute_metrics`` is the last evaluation (marl-eval's protocol evaluates the best policy again on 10x
the episodes; this is the policy the run ended with). Every run of a task has the steps its method's
runs share, since marl-eval reads the step keys of one run for all.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from mcrs.env.core import METRICS
from mcrs.experiment.util.atomic import write_text_atomic
from mcrs_lab.analysis.runs import TrainingRun, run_labels

ENVIRONMENT = "mcrs"


def marl_eval_data(training: list[TrainingRun]) -> dict[str, Any]:
    """The marl-eval structure of ``training`` (all maps: one task each); runs without evaluations are
    left out."""
    by_map: dict[str, list[TrainingRun]] = {}
    for run in training:
        by_map.setdefault(run.env_name, []).append(run)
    labels = {path: label for runs in by_map.values() for path, label in run_labels(runs).items()}
    out: dict[str, Any] = {}
    by_method: dict[tuple[str, str], list[TrainingRun]] = {}
    for run in sorted(training, key=lambda r: (r.seed, str(r.path))):
        by_method.setdefault((run.env_name, labels[run.path]), []).append(run)
    for (task, label), runs in sorted(by_method.items()):
        series = {run.path: _evaluations(run) for run in runs}
        series = {path: s for path, s in series.items() if s}
        if not series:
            continue
        common = sorted(set.intersection(*(set(s) for s in series.values())))
        if not common:
            continue
        algorithm: dict[str, Any] = {}
        for k, values in enumerate(series.values()):
            run_data: dict[str, Any] = {
                f"step_{i}": {"step_count": int(step), **{m: [v] for m, v in values[step].items()}}
                for i, step in enumerate(common)
            }
            run_data["absolute_metrics"] = {m: [v] for m, v in values[common[-1]].items()}
            algorithm[f"run_{k}"] = run_data
        out.setdefault(ENVIRONMENT, {}).setdefault(task, {})[label] = algorithm
    return out


def _evaluations(run: TrainingRun) -> dict[int, dict[str, float]]:
    """``{env step: {metric: value}}`` of the run's greedy evaluations, every metric logged at that step."""
    by_step: dict[int, dict[str, float]] = {}
    for metric in METRICS:
        found = run.scalar(f"eval/{metric}")
        if found is None:
            continue
        for step, value in zip(*found, strict=True):
            by_step.setdefault(int(step), {})[metric] = float(value)
    complete = {m for values in by_step.values() for m in values}
    return {s: v for s, v in by_step.items() if set(v) == complete and np.isfinite(list(v.values())).all()}


def write_marl_eval(path: Path, training: list[TrainingRun]) -> dict[str, Any]:
    """Write :func:`marl_eval_data` as JSON to ``path``; returns it."""
    data = marl_eval_data(training)
    write_text_atomic(path, json.dumps(data, indent=1) + "\n")
    return data
