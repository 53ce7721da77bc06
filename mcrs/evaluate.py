"""``mcrs-eval``: evaluate policies on a map and report every episode metric.

The K episodes run as one batch of K environments, in chunks of at most ``MAX_BATCH``. Results go to the
Hydra run directory: ``metrics.csv`` (mean and std per policy), ``episodes.csv``, ``summary.md`` and, with
``figures=true``, ``scene.png``, ``uncertainty_contours.png`` and ``episode.gif``.

    mcrs-eval policy=all episodes=32
    mcrs-eval env=map20 env.comm_range=0 policy=lawnmower episodes=8
    mcrs-eval policy=outputs/map10/qmix/<run>/checkpoints/model_000500000.pt    (a trained agent)
    mcrs-eval policy=outputs/map10/qmix/<run> heuristics=true    (it and every heuristic, same episodes)

A trained policy plays its training's evaluation episodes unless ``seed=`` or ``episodes=`` says otherwise,
and tables name it by its run (:mod:`mcrs.policies.identity`)."""

from __future__ import annotations

import csv
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import torch
from hydra.core.config_store import ConfigStore
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from mcrs.env.config import EnvConfig, ScenarioConfig, device_problem
from mcrs.env.metrics import METRIC_LABELS, METRICS
from mcrs.env.torchrl_env import MCRSEnv
from mcrs.experiment.commands.cli import one_line_errors, remove_refused_dirs
from mcrs.experiment.run.checkpoint import CheckpointError
from mcrs.experiment.run.logging import progress_bar, read_scalar_rows, scalar_file, sorted_points
from mcrs.experiment.run.rundir import describe_os_error, register_resolvers
from mcrs.experiment.schema import CONFIG_DIR, MAX_EVAL_EPISODES, MAX_SEED
from mcrs.experiment.training import evaluation
from mcrs.experiment.util.messages import ranked
from mcrs.experiment.util.tables import markdown, mean_std
from mcrs.experiment.util.threads import apply_threads, cpu_count, threads_problem
from mcrs.policies import POLICIES, check_policy, make_policy, policy_env
from mcrs.policies.export import read_description
from mcrs.policies.identity import default_episodes_seed, policy_label, run_task_name
from mcrs.policies.task_runs import evaluate_task_run, load_task_run, task_node
from mcrs.policies.trained import is_exported, looks_like_checkpoint, resolve_checkpoint

ALL = "all"
log = logging.getLogger(__name__)
MAX_BATCH = 512  # environments per batch; bounds memory on the largest map
#: Said under every table of summary.md: what a cell holds and which way is better.
LEGEND = (
    "Each cell: mean ± standard deviation over the episodes, of the value at the end of each episode. "
    "Higher is better for episode reward, targets found and coverage; lower for final uncertainty, false "
    "discoveries, collisions and no-fly violations."
)
TASK_LEGEND = "Each cell: mean ± standard deviation over the episodes. Higher episode reward is better."


@dataclass
class EvalConfig:
    """The ``mcrs-eval`` config (``conf/eval.yaml``), with which Hydra refuses unknown keys and wrong types."""

    env: ScenarioConfig = field(default_factory=ScenarioConfig)  # the scenario (conf/env/ presets)
    policy: str = "greedy"  # random | lawnmower | greedy | coverage | all | a checkpoint or run directory
    heuristics: bool = False  # true: every heuristic beside the policy, on the same episodes
    episodes: int | None = None  # K episodes (batches of K environments); None: see default_episodes_seed
    seed: int | None = None  # seeds the environments and the policy's generator; None: as episodes
    figures: bool = True  # scene.png, uncertainty_contours.png, episode.gif
    device: str = "cpu"  # where the environments run
    threads: str = "auto"  # torch CPU threads: auto (the cores the load leaves free), 0 (torch's: all) or N


ConfigStore.instance().store(name="mcrs_eval_config", node=EvalConfig)
register_resolvers()  # ${mcrs.num:...} in the sweep directory names (conf/study/comm_range.yaml)


def eval_errors(cfg: EvalConfig | DictConfig) -> list[str]:
    """Return the problems of an evaluation config, each naming the field and what is allowed."""
    errors = []
    if cfg.episodes is not None and cfg.episodes < 1:
        errors.append(f"episodes={cfg.episodes}: must be >= 1")
    elif cfg.episodes is not None and cfg.episodes > MAX_EVAL_EPISODES:
        errors.append(
            f"episodes={cfg.episodes}: at most {MAX_EVAL_EPISODES} (every episode's metrics are kept): "
            "evaluate more as several runs with other seeds"
        )
    if cfg.seed is not None and not 0 <= cfg.seed <= MAX_SEED:
        errors.append(f"seed={cfg.seed}: must be in [0, 2**63 - 1]")
    problem = device_problem(cfg.device)
    if problem:
        errors.append(f"device={cfg.device!r}: {problem}")
    problem = threads_problem(cfg.threads, cpu_count())
    if problem:
        errors.append(f"threads={cfg.threads}: {problem}")
    return errors


def job_errors(cfg: DictConfig, overrides: list[str]) -> list[str]:
    """Return what an evaluation would be refused for: its values, its scenario and its policy.
    ``conf/eval.yaml`` names it as the ``validate`` of :class:`~mcrs.experiment.commands.cli.RunDirCheck`,
    so a sweep checks every job before the first starts."""
    errors = eval_errors(cfg)
    try:
        env_config = EnvConfig.from_scenario(cfg.env, num_envs=1, device="cpu")
    except (ValueError, TypeError) as error:  # one line per job: "invalid environment config: <field>: ..."
        errors.append(" ".join(line.strip().removeprefix("- ") for line in str(error).splitlines()))
        env_config = None
    try:
        for name in policy_names(str(cfg.policy), bool(cfg.get("heuristics", False))):
            if env_config is not None:
                check_policy(name, env_config)  # a checkpoint of another map or team: its config only
    except ValueError as error:
        errors.append(str(error))
    return errors


def policy_names(policy: str, heuristics: bool = False) -> list[str]:
    """Return the policies a ``policy=`` value stands for, then every heuristic with ``heuristics``."""
    names = _policy_names(policy)
    return [*names, *(p for p in POLICIES if p not in names)] if heuristics else names


def _policy_names(policy: str) -> list[str]:
    if policy == ALL:
        return list(POLICIES)
    if policy not in POLICIES and looks_like_checkpoint(policy):
        if not resolve_checkpoint(policy).is_file():  # before any episode runs or progress is shown
            raise ValueError(
                f"policy={policy}: no checkpoint there (a run directory with checkpoints/, a .pt file or an "
                f"exported .pt2); "
                f"or one of {[*sorted(POLICIES), ALL]}"
            )
        if is_exported(policy):  # not an exported agent: refused here too, before any progress is shown
            read_description(policy)
        return [policy]
    if policy not in POLICIES:
        allowed = ", ".join(ranked(policy, [*sorted(POLICIES), ALL]))  # closest first
        raise ValueError(
            f"unknown policy {policy!r}; allowed: {allowed}, or a checkpoint (a run directory or a .pt "
            "file) or an exported agent (.pt2)"
        )
    return [policy]


def episode_metrics(
    env_config: EnvConfig,
    policy_name: str,
    episodes: int,
    seed: int,
    max_batch: int = MAX_BATCH,
    progress: Any = None,
) -> dict[str, torch.Tensor]:
    """Return the final value of every metric for each of ``episodes`` episodes as ``{name: [K]}`` on CPU.
    ``progress`` advances by one per step of the batched environments."""
    if episodes < 1:
        raise ValueError(f"episodes={episodes}: must be >= 1")
    batch = min(episodes, max_batch)
    cfg = policy_env(policy_name, env_config.replace(num_envs=batch, expose_beliefs=False))
    env = MCRSEnv(cfg)
    policy = make_policy(policy_name, cfg, seed)
    # the environments are seeded once: each further batch goes on from where the generator stands
    step = None if progress is None else (lambda: progress.update(1))
    chunks = [
        evaluation.final_metrics(env, policy, seed if k == 0 else None, on_step=step)
        for k in range(math.ceil(episodes / batch))
    ]
    return {name: torch.cat([chunk[name] for chunk in chunks])[:episodes] for name in METRICS}


def evaluate_episodes(
    env_config: EnvConfig, names: list[str], episodes: int, seed: int, description: str, enabled: bool = True
) -> dict[str, dict[str, torch.Tensor]]:
    """Run :func:`episode_metrics` for each policy in ``names`` under one progress bar."""
    for name in names:  # a checkpoint of another map or team: refused before the bar's first line
        check_policy(name, env_config)
    chunks = math.ceil(episodes / min(episodes, MAX_BATCH))
    total = len(names) * chunks * env_config.max_steps
    per_episode = {}
    with progress_bar(total, 0, enabled, description) as bar:
        for name in names:
            bar.set_postfix(policy=Path(name).name if name not in POLICIES else name, refresh=False)
            per_episode[name] = episode_metrics(env_config, name, episodes, seed, progress=bar)
    return per_episode


def summarize(values: dict[str, torch.Tensor]) -> dict[str, tuple[float, float]]:
    """Return the mean and sample standard deviation over episodes; the std of one episode is 0."""
    return evaluation.summarize(values, correction=evaluation.SAMPLE_STD)


def evaluate_policy(
    env_config: EnvConfig | ScenarioConfig, policy_name: str, episodes: int, seed: int
) -> dict[str, tuple[float, float]]:
    """Return ``{metric: (mean, std)}`` of ``policy_name`` on an :class:`EnvConfig` or a scenario, played on
    CPU."""
    if isinstance(env_config, ScenarioConfig):
        env_config = EnvConfig.from_scenario(env_config)
    elif not isinstance(env_config, EnvConfig):
        raise TypeError(
            f"env_config: expected an EnvConfig (experiment.env_config) or a ScenarioConfig (config.env), "
            f"got {type(env_config).__name__}"
        )
    return summarize(episode_metrics(env_config, policy_name, episodes, seed))


def format_table(results: dict[str, dict[str, tuple[float, float]]]) -> str:
    """Return a markdown table with one row per policy and a ``mean ± std`` column per metric."""
    header = ["policy", *(METRIC_LABELS[m] for m in METRICS)]
    return markdown(header, [[name] + [mean_std(*r[m]) for m in METRICS] for name, r in results.items()])


def describe(env_config: EnvConfig, episodes: int, seed: int) -> str:
    c = env_config
    return (
        f"{c.name}: {c.width}x{c.height} grid, {c.n_uavs} UAVs, {c.n_targets} targets, {c.n_no_fly} no-fly "
        f"zones, T={c.max_steps}, R_c={c.comm_range:g}, comm_rounds={c.comm_rounds}; "
        f"{episodes} episodes, seed {seed}"
    )


def write_results(
    out_dir: Path,
    env_config: EnvConfig,
    seed: int,
    per_episode: dict[str, dict[str, torch.Tensor]],
    results: dict[str, dict[str, tuple[float, float]]],
    title: str,
    table: str,
) -> None:
    """Write ``metrics.csv`` (with the map, R_c and seed that ``mcrs-report`` groups by), ``episodes.csv`` and
    ``summary.md``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    with open(out_dir / "metrics.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(
            [
                "policy",
                "env",
                "comm_range",
                "seed",
                "episodes",
                *(f"{m}_{s}" for m in METRICS for s in ("mean", "std")),
            ]
        )
        for name, r in results.items():
            episodes = len(next(iter(per_episode[name].values())))
            writer.writerow(
                [
                    name,
                    env_config.name,
                    f"{env_config.comm_range:g}",
                    seed,
                    episodes,
                    *(f"{v:.6g}" for m in METRICS for v in r[m]),
                ]
            )
    with open(out_dir / "episodes.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["policy", "episode", *METRICS])
        for name, values in per_episode.items():
            columns = torch.stack([values[m].to(torch.float64) for m in METRICS], dim=-1).tolist()
            for k, row in enumerate(columns):
                writer.writerow([name, k, *(f"{v:.6g}" for v in row)])
    (out_dir / "summary.md").write_text(f"# Evaluation\n\n{title}\n\n{table}\n\n{LEGEND}\n")


def write_figures(out_dir: Path, env_config: EnvConfig, policy_name: str, seed: int) -> list[Path]:
    """Draw the three pictures of one episode of ``policy_name`` (:mod:`mcrs.viz`)."""
    from mcrs.viz import write_episode_pictures  # deferred: matplotlib, only when drawing

    return write_episode_pictures(out_dir, env_config, policy_name, seed)


def run(cfg: DictConfig, out_dir: Path) -> dict[str, dict[str, tuple[float, float]]]:
    """Evaluate as configured, print the table and write the results and figures into ``out_dir``."""
    errors = eval_errors(cfg)
    if errors:
        raise ValueError("invalid config: " + "; ".join(errors))
    names = policy_names(str(cfg.policy), bool(cfg.get("heuristics", False)))
    apply_threads(cfg.threads)
    given = zip((cfg.episodes, cfg.seed), default_episodes_seed(names), strict=True)  # None: the default
    episodes, seed = (int(d if v is None else v) for v, d in given)
    if task_node(names[0]) is not None:  # a run of another task than MCRS: beside its random baseline
        return run_task(names[0], episodes, seed, str(cfg.device), out_dir, shown=policy_label(names[0]))
    env_config = EnvConfig.from_scenario(cfg.env, num_envs=min(episodes, MAX_BATCH), device=str(cfg.device))
    per_episode = evaluate_episodes(env_config, names, episodes, seed, "mcrs-eval")
    results = {name: summarize(values) for name, values in per_episode.items()}
    title = describe(env_config, episodes, seed)
    labels = {name: policy_label(name) for name in names}
    table = format_table({labels[name]: r for name, r in results.items()})
    _say(f"{title}\n\n{table}\n")
    write_results(out_dir, env_config, seed, per_episode, results, title, table)
    if cfg.figures:
        for name in names:
            print(f"drawing one episode of {labels[name]} ...", flush=True)
            folder = out_dir if len(names) == 1 else out_dir / Path(labels[name].split(" ")[0]).name
            paths = write_figures(folder, env_config, name, seed)
            _say("figures: " + ", ".join(str(p) for p in paths))
    _say(f"results in {out_dir}")
    return results


def run_task(
    policy: str,
    episodes: int,
    seed: int,
    device: str,
    out_dir: Path,
    label: str | None = None,
    shown: str | None = None,
) -> dict[str, dict[str, tuple[float, float]]]:
    """Evaluate a run of another task than MCRS: the trained agent and the random baseline on the same
    episodes. The table is printed and written like ``mcrs-eval``'s. ``label`` names the trained agent in
    the files (its path when None), ``shown`` in the printed table."""
    try:
        run = load_task_run(policy)
    except CheckpointError as error:
        raise ValueError(str(error)) from None
    name = label or str(policy)
    print(
        f"evaluating {shown or name} and the random baseline on {episodes} episodes of {run.task.name} ...",
        flush=True,
    )
    per_episode = evaluate_task_run(run, min(episodes, MAX_EVAL_EPISODES), seed, device, name)
    results = {policy_name: summarize(values) for policy_name, values in per_episode.items()}
    metrics = list(next(iter(per_episode.values())))
    names = {name: shown} if shown else {}
    table = markdown(
        ["policy", *metrics],
        [[names.get(p, p)] + [mean_std(*r[m]) for m in metrics] for p, r in results.items()],
    )
    title = f"{run.task.name} ({run.config['task'].get('_target_')}): {episodes} episodes, seed {seed}"
    _say(f"{title}\n\n{table}\n")
    out_dir.mkdir(parents=True, exist_ok=True)
    with open(out_dir / "metrics.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(
            ["policy", "task", "seed", "episodes", *(f"{m}_{s}" for m in metrics for s in ("mean", "std"))]
        )
        for policy_name, r in results.items():
            row = [f"{v:.6g}" for m in metrics for v in r[m]]
            writer.writerow([policy_name, run.task.name, seed, episodes, *row])
    with open(out_dir / "episodes.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["policy", "episode", *metrics])
        for policy_name, values in per_episode.items():
            for k, row in enumerate(torch.stack([values[m] for m in metrics], dim=-1).tolist()):
                writer.writerow([policy_name, k, *(f"{v:.6g}" for v in row)])
    (out_dir / "summary.md").write_text(f"# Evaluation\n\n{title}\n\n{table}\n\n{TASK_LEGEND}\n")
    _say(f"results in {out_dir}")
    return results


REPORT_DIR = "report"  # a training run's report (evaluate_run), inside its run directory


@dataclass(frozen=True)
class RunReport:
    """What :func:`evaluate_run` wrote, and the episode rewards it measured as ``{label: (mean, std)}``."""

    table: Path
    curve: Path
    gif: Path
    rewards: dict[str, tuple[float, float]]


def evaluate_run(
    run_dir: Path, env_config: EnvConfig, label: str, episodes: int, seed: int, progress: bool = True
) -> RunReport:
    """Compare a finished training run with the heuristics in ``run_dir/report/``.

    It writes the tables of ``mcrs-eval`` for the greedy trained policy and every heuristic on the same
    episodes, the learning curves with the heuristics as lines and one episode's pictures. ``label`` names
    the trained policy; ``progress`` is shown while the episodes run."""
    from mcrs.viz.learning_curves import (
        CURVE_METRICS,
        Reference,
        confidence_half_width,
        curve_of,
        plot_curves,
    )

    out = run_dir / REPORT_DIR
    env_config = env_config.replace(num_envs=min(episodes, MAX_BATCH))
    names = [str(run_dir), *POLICIES]  # the CSV names the trained policy by its run, as mcrs-eval does
    per_episode = evaluate_episodes(env_config, names, episodes, seed, "report", progress)
    results = {name: summarize(values) for name, values in per_episode.items()}
    labelled = {label if name == str(run_dir) else f"{name} (heuristic)": r for name, r in results.items()}
    table = format_table(labelled)
    write_results(out, env_config, seed, per_episode, results, describe(env_config, episodes, seed), table)

    panels: dict[str, dict] = {}
    for metric, panel in CURVE_METRICS.items():
        path = scalar_file(run_dir, metric)
        curve = curve_of(label, [sorted_points(read_scalar_rows(path))]) if path.is_file() else None
        panels[panel] = {label: curve} if curve is not None else {}
    references: dict[str, list[Reference]] = {}
    for name in POLICIES:
        for metric, panel in CURVE_METRICS.items():
            values = per_episode[name][metric.split("/")[-1]].to(torch.float64).numpy()
            half = float(confidence_half_width(values[:, None])[0])
            references.setdefault(panel, []).append(
                Reference(f"{name} (heuristic)", float(np.mean(values)), half, len(values), "episodes")
            )
    curve = plot_curves(
        panels,
        out / "learning_curves.png",
        f"{env_config.name}: evaluations of the trained policy (greedy actions)",
        [label],
        references,
    )
    pictures = write_figures(out, env_config.replace(num_envs=1), str(run_dir), seed)
    rewards = {name: r["episode_reward"] for name, r in labelled.items()}
    return RunReport(out / "summary.md", curve, pictures[-1], rewards)


def evaluate_task_report(
    run_dir: Path, label: str, episodes: int, seed: int, device: str = "cpu"
) -> tuple[Path, Path, dict[str, tuple[float, float]]]:
    """Write the ``report=true`` report of a run of another task than MCRS into ``run_dir/report/``.

    It evaluates as :func:`run_task` and draws every logged metric with the random baseline as a line.
    Returns the table, the curve and the episode rewards ``{label: (mean, std)}``."""
    from mcrs.viz.learning_curves import Reference, confidence_half_width, curve_of, plot_curves

    out = run_dir / REPORT_DIR
    results = run_task(str(run_dir), episodes, seed, device, out, label)
    per_episode = {}  # the random baseline's episodes, from the table just written
    with open(out / "episodes.csv", newline="") as f:
        for row in csv.DictReader(f):
            if row["policy"] == "random":
                for metric, value in row.items():
                    if metric not in ("policy", "episode"):
                        per_episode.setdefault(metric, []).append(float(value))
    panels: dict[str, dict] = {}
    references: dict[str, list[Reference]] = {}
    for metric, values in per_episode.items():
        path = scalar_file(run_dir, f"eval/{metric}")
        if not path.is_file():
            continue
        panels[metric] = {label: curve_of(label, [sorted_points(read_scalar_rows(path))])}
        array = np.asarray(values)
        half = float(confidence_half_width(array[:, None])[0])
        references[metric] = [Reference("random", float(array.mean()), half, len(array), "episodes")]
    task = run_task_name(run_dir)
    curve = plot_curves(
        panels,
        out / "learning_curves.png",
        f"{task}: evaluations of the trained policy (greedy actions)",
        [label],
        references,
    )
    return out / "summary.md", curve, {name: r["episode_reward"] for name, r in results.items()}


def _say(message: str) -> None:
    """Print a result and keep it in the run's log."""
    print(message, flush=True)
    log.info("%s", message, extra={"console": False})


@one_line_errors("mcrs-eval")
@hydra.main(config_path=CONFIG_DIR, config_name="eval", version_base=None)
def main(cfg: DictConfig) -> None:
    """Console entry point ``mcrs-eval`` (Hydra ``key=value`` overrides, ``--help``, ``-m`` sweeps)."""
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        run(cfg, out_dir)
    except ValueError as error:  # bad input: one clear message, no traceback, no directory left
        remove_refused_dirs(out_dir)
        raise SystemExit(f"mcrs-eval: error: {error}") from None
    except OSError as error:  # a full disk, a read-only folder: one line, not the trace of the write
        raise SystemExit(f"mcrs-eval: error: cannot write {out_dir}: {describe_os_error(error)}") from None


if __name__ == "__main__":
    main()
