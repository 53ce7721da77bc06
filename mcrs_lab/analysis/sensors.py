"""The sensor's share of the gap: the heuristics and the reward bound at each sensor model evaluated.

Our sensor (``p_detect``, ``p_false_alarm``) is a choice where the paper is silent. Given heuristic
evaluations of one map at several sensor models (each record keeps the env config it ran), the table gives,
per sensor, each heuristic's episode reward, targets found and false discoveries (mean ± std over
evaluation seeds), and the reward bound on the same layouts (:mod:`mcrs_lab.analysis.bound`): with the
sensor in the team's favour, and with a sensor that never errs.
"""

from __future__ import annotations

import numpy as np

from mcrs.env.config import from_mapping, with_legacy_values
from mcrs.experiment.util.tables import markdown
from mcrs.policies import POLICIES
from mcrs_lab.analysis.bound import reward_bound
from mcrs_lab.analysis.runs import EvaluationRow

SENSOR_FIELDS = ("p_detect", "p_false_alarm")
METRICS = ("episode_reward", "targets_found", "false_discoveries")


def sensor_of(row: EvaluationRow) -> tuple[float, float] | None:
    """``(p_detect, p_false_alarm)`` of the scenario a row ran, None when its config is unknown."""
    if row.env is None or any(not isinstance(row.env.get(f), (int, float)) for f in SENSOR_FIELDS):
        return None
    return float(row.env["p_detect"]), float(row.env["p_false_alarm"])


def _mean_std(values: list[float]) -> str:
    std = float(np.std(values, ddof=1)) if len(values) > 1 else 0.0
    return f"{np.mean(values):.2f} ± {std:.2f}"


def _bounds(row: EvaluationRow, seeds: list[int]) -> tuple[float, float]:
    """The bound and the never-erring sensor's bound on the row's scenario, averaged over ``seeds``."""
    config = from_mapping({**with_legacy_values(dict(row.env or {}))[0], "num_envs": 1, "device": "cpu"})
    perfect = config.replace(p_detect=1.0, p_false_alarm=0.0)
    strict = [float(reward_bound(config, row.episodes, s).mean()) for s in seeds]
    exact = [float(reward_bound(perfect, row.episodes, s).mean()) for s in seeds]
    return float(np.mean(strict)), float(np.mean(exact))


def sensor_table(evaluations: list[EvaluationRow], env_name: str) -> str | None:
    """The markdown table of the heuristics of ``env_name`` by sensor model; None unless two or more sensor
    models were evaluated."""
    rows = [r for r in evaluations if r.is_heuristic and r.env_name == env_name and sensor_of(r) is not None]
    sensors = sorted({sensor_of(r) for r in rows}, key=lambda s: (s[0], -s[1]))
    if len(sensors) < 2:
        return None
    body = []
    for sensor in sensors:
        group = [r for r in rows if sensor_of(r) == sensor]
        name = f"{sensor[0]:g} / {sensor[1]:g}"
        order = list(POLICIES)  # random, lawnmower, greedy, coverage: the heuristics' own order
        for policy in sorted(
            {r.policy for r in group}, key=lambda p: (order.index(p) if p in order else len(order), p)
        ):
            mine = [r for r in group if r.policy == policy]
            body.append(
                [name, policy, str(len(mine))]
                + [_mean_std([r.means[m] for r in mine if m in r.means]) for m in METRICS]
            )
        strict, exact = _bounds(group[0], sorted({r.seed for r in group}))
        seeds = str(len({r.seed for r in group}))
        body.append([name, "bound (sensor in the team's favour)", seeds, f"{strict:.2f}", "", ""])
        body.append([name, "bound (a sensor that never errs)", seeds, f"{exact:.2f}", "", ""])
    header = [
        "p_detect / p_false_alarm",
        "policy",
        "seeds",
        "episode reward",
        "targets found",
        "false discoveries",
    ]
    return markdown(header, body)
