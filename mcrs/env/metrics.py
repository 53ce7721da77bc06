"""The episode metrics every environment reports, with the labels tables and figures give them."""

METRICS = (
    "episode_reward",
    "uncertainty",
    "targets_found",
    "false_discoveries",
    "collisions",
    "no_fly_violations",
    "coverage",
)
#: How tables and figures name each metric.
METRIC_LABELS = {
    "episode_reward": "episode reward",
    "uncertainty": "final uncertainty",
    "targets_found": "targets found",
    "false_discoveries": "false discoveries",
    "collisions": "collisions",
    "no_fly_violations": "no-fly violations",
    "coverage": "coverage",
}
#: Which way each metric is better: what "a learner beats a heuristic" means on it.
METRIC_BETTER = {
    "episode_reward": "higher",
    "uncertainty": "lower",
    "targets_found": "higher",
    "false_discoveries": "lower",
    "collisions": "lower",
    "no_fly_violations": "lower",
    "coverage": "higher",
}
