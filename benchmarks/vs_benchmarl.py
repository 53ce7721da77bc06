"""Our QMIX beside BenchMARL's on one VMAS task (``mcrs-bench-benchmarl``): learning curve and wall clock.

Why: BenchMARL is the reference TorchRL-based MARL library; a user choosing between the two wants to know
what our recurrent, episode-replay QMIX learns and costs per env step next to BenchMARL's QMIX on the same
task, with the same network widths, batch, learning rate, exploration, target updates and budget.

Both sides train on VMAS ``navigation`` (discrete actions, the same scenario settings, seed and number of
frames: one frame is one env step of one environment, a team transition). Ours runs in this process
(:class:`mcrs.Experiment` with :class:`mcrs.tasks.vmas.VmasTask`); BenchMARL pins an older TorchRL, so it
runs in its own virtual environment (``--benchmarl-python``) through ``benchmarks/benchmarl_side.py``, with
the settings passed as JSON. Printed and recorded: each side's greedy evaluation (the team's return: the
agents' rewards summed, over each episode up to its first done) at the same frame counts, and wall seconds
per 100k frames with and without the evaluations. A side that cannot run is recorded with its error (the
JSON's ``valid: false`` and ``note``), not skipped silently.

    nice -n 19 mcrs-bench-benchmarl                        # both sides, 100k frames each
    mcrs-bench-benchmarl --sides ours --quick --json none  # a smoke test of our side
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from mcrs_benchmarks.benchmarl_side import benchmarl_fields
from mcrs_benchmarks.harness import Report, make_parser, require_at_least, run_benchmark

DEFAULT_PYTHON = "/work/bmvenv/bin/python"
SIDES = ("ours", "benchmarl")
LABELS = {"ours": "ours (GRU, episodes)", "benchmarl": "BenchMARL (MLP, transitions)"}
#: BenchMARL's ``navigation`` task config, with collisions off as in ``task=vmas_navigation``: passed to
#: VMAS by both sides, so that neither falls back on a default the other does not share.
SCENARIO_KWARGS: dict[str, Any] = {
    "n_agents": 3,
    "collisions": False,
    "agents_with_same_goal": 1,
    "split_goals": False,
    "observe_all_goals": False,
    "shared_rew": False,
    "lidar_range": 0.35,
    "agent_radius": 0.1,
}
PER_FRAMES = 100_000  # wall seconds are quoted per this many frames
TAIL = 0.2  # the end of the curve: the evaluations in the last fifth of the frames
BENCHMARL_TIMEOUT_S = 3600


@dataclass(frozen=True)
class Settings:
    """What both sides share: the task, the budget and the learner's settings, in frames (env steps)."""

    scenario: str = "navigation"
    max_steps: int = 50
    scenario_kwargs: dict[str, Any] = field(default_factory=lambda: dict(SCENARIO_KWARGS))
    seed: int = 0
    frames: int = 100_000
    n_envs: int = 16  # environments per collection: n_envs * max_steps frames
    batch_episodes: int = 32  # ours: whole episodes per update; BenchMARL: as many transitions
    updates_per_batch: int = 16  # updates after each collection
    replay_episodes: int = 5000
    eval_interval: int = 4000
    eval_episodes: int = 32
    lr: float = 1e-3  # Adam, both (what task=vmas_navigation learned with in docs/TRAINING.md)
    adam_eps: float = 1e-6
    gamma: float = 0.99
    grad_clip: float = 10.0  # gradient norm
    hidden: int = 64  # ours: Linear -> GRU -> Linear; BenchMARL: an MLP of two layers of this width
    mixing_embed_dim: int = 32  # one-layer hypernetworks on both sides (TorchRL's QMixer)
    eps_start: float = 1.0
    eps_end: float = 0.05
    eps_anneal_frames: int = 33_333  # linear; a third of the frames, BenchMARL's default
    target_update_updates: int = 80  # hard copy of the target networks every this many updates
    threads: int = 1

    @property
    def frames_per_batch(self) -> int:
        return self.n_envs * self.max_steps

    def problems(self) -> list[str]:
        """What would make the two runs differ in budget or schedule, one line each (empty: none)."""
        out = []
        batch = self.frames_per_batch
        for name in ("frames", "eval_interval"):
            if getattr(self, name) % batch:
                out.append(
                    f"{name}={getattr(self, name)} is not a whole number of collections of {batch} frames"
                )
        if self.eval_interval and self.frames % self.eval_interval:
            out.append(f"frames={self.frames} is not a whole number of eval_interval={self.eval_interval}")
        if (self.target_update_updates * self.n_envs) % self.updates_per_batch:
            out.append(
                f"target_update_updates={self.target_update_updates} is not a whole number of episodes at "
                f"{self.updates_per_batch} updates per {self.n_envs} episodes"
            )
        return out


QUICK = {
    "max_steps": 10,
    "frames": 80,
    "n_envs": 4,
    "batch_episodes": 4,
    "updates_per_batch": 4,
    "eval_interval": 40,
    "eval_episodes": 4,
    "eps_anneal_frames": 40,
    "target_update_updates": 4,
}


def ours_overrides(s: Settings) -> list[str]:
    """The ``mcrs-train`` overrides of our side (its task is :class:`~mcrs.tasks.vmas.VmasTask`).

    ``algo.reward_scale = 1 / n_agents``: our team reward is the agents' sum, BenchMARL's QMIX trains on
    their mean, so the targets, the values and the gradient clip see the same numbers."""
    return [
        "algo=qmix",
        f"seed={s.seed}",
        f"threads={s.threads}",
        f"algo.gamma={s.gamma}",
        f"algo.mixing_embed_dim={s.mixing_embed_dim}",
        "algo.hypernet_layers=1",
        "algo.td_lambda=0.0",
        "algo.double_q=false",  # TorchRL's QMixerLoss: the target network's own max
        "algo.time_limit=terminal",  # TorchRL's VmasEnv marks max_steps as terminated
        f"algo.reward_scale={1.0 / s.scenario_kwargs['n_agents']!r}",
        f"model.hidden_dim={s.hidden}",
        "model.agent_id=false",  # BenchMARL's shared MLP sees the observation only
        "model.last_action=false",
        f"train.total_env_steps={s.frames}",
        f"train.num_envs={s.n_envs}",
        f"train.batch_episodes={s.batch_episodes}",
        f"train.updates_per_episode={s.updates_per_batch / s.n_envs!r}",
        f"train.replay_episodes={s.replay_episodes}",
        "train.optimizer=adam",
        f"train.lr={s.lr}",
        f"train.optim_eps={s.adam_eps}",
        f"train.grad_clip={s.grad_clip}",
        f"train.eps_start={s.eps_start}",
        f"train.eps_end={s.eps_end}",
        f"train.eps_anneal_steps={s.eps_anneal_frames}",
        f"train.target_update_episodes={s.target_update_updates * s.n_envs // s.updates_per_batch}",
        f"train.eval_interval={s.eval_interval}",
        f"train.eval_episodes={s.eval_episodes}",
        f"train.checkpoint_interval={s.frames * 10}",
        "train.checkpoint_minutes=0",
        "train.save_replay=false",
        "logger.progress_bar=false",
    ]


@dataclass
class SideResult:
    """One side's run: its evaluations ``(frames, team return)``, clocks and what stopped it, if anything."""

    evaluations: list[tuple[int, float]] = field(default_factory=list)
    frames: int = 0
    wall_s: float = float("nan")
    eval_s: float = float("nan")
    versions: dict[str, str] = field(default_factory=dict)
    error: str = ""

    def seconds_per(self, frames: int = PER_FRAMES, with_eval: bool = False) -> float:
        """Wall seconds per ``frames`` frames (training: collection and updates; ``with_eval``: all)."""
        if not self.frames:
            return float("nan")
        seconds = self.wall_s if with_eval else self.wall_s - self.eval_s
        return seconds * frames / self.frames

    @property
    def final_return(self) -> float:
        return self.evaluations[-1][1] if self.evaluations else float("nan")

    def tail_return(self, fraction: float = TAIL) -> float:
        """The mean team return of the evaluations in the last ``fraction`` of the frames: one evaluation
        of 32 episodes is noisy, the last few together less so."""
        since = self.frames * (1.0 - fraction)
        tail = [value for frames, value in self.evaluations if frames >= since]
        return sum(tail) / len(tail) if tail else float("nan")


def run_ours(s: Settings) -> SideResult:
    """Our QMIX through :class:`mcrs.Experiment` in a temporary run directory."""
    import torch

    import mcrs
    from mcrs.experiment.training.callbacks import Callback
    from mcrs.tasks.vmas import VmasTask

    evaluations: list[tuple[int, float]] = []

    class Curve(Callback):
        """The greedy evaluation's team return at each evaluation, at the env steps collected so far."""

        def on_evaluation_end(self, metrics: dict[str, float]) -> None:
            evaluations.append((int(self.experiment.counters.env_steps), float(metrics["episode_reward"])))

    task = VmasTask(s.scenario, s.max_steps, dict(s.scenario_kwargs))
    config = mcrs.compose(*ours_overrides(s))
    config.overwrite = True
    with tempfile.TemporaryDirectory() as run_dir:
        experiment = mcrs.Experiment(config, Path(run_dir), task=task, callbacks=[Curve()])
        start = time.perf_counter()
        experiment.run()
        wall = time.perf_counter() - start
    import torchrl

    return SideResult(
        evaluations,
        int(experiment.counters.env_steps),
        wall,
        float(experiment.seconds["eval"]),  # the trainer's own clock around its evaluations
        {
            "mcrs": _installed("mcrs"),
            "torchrl": torchrl.__version__,
            "torch": torch.__version__,
        },
    )


def run_benchmarl(s: Settings, python: str, timeout_s: float = BENCHMARL_TIMEOUT_S) -> SideResult:
    """BenchMARL's QMIX in its own environment: ``python benchmarl_side.py``; its error, if it fails."""
    script = Path(__file__).resolve().parent / "benchmarl_side.py"
    with tempfile.TemporaryDirectory() as folder:
        settings_path, result_path = Path(folder) / "settings.json", Path(folder) / "result.json"
        settings_path.write_text(json.dumps(asdict(s)))
        env = {**os.environ, "PYTHONWARNINGS": "ignore"}
        env.pop("PYTHONPATH", None)  # BenchMARL's own packages, not ours
        try:
            done = subprocess.run(
                [python, str(script), str(settings_path), str(result_path)],
                capture_output=True,
                text=True,
                timeout=timeout_s,
                env=env,
                check=False,
                cwd=folder,
            )
        except (OSError, subprocess.TimeoutExpired) as error:
            return SideResult(error=f"{python}: {error}")
        if done.returncode != 0 or not result_path.exists():
            tail = [line for line in (done.stderr or done.stdout).strip().splitlines() if line.strip()]
            last = tail[-1] if tail else "no output"
            return SideResult(error=f"{python} exited with {done.returncode}: {last}")
        data = json.loads(result_path.read_text())
    return SideResult(
        [(int(e["frames"]), float(e["return"])) for e in data["evaluations"]],
        int(data["frames"]),
        float(data["wall_s"]),
        float(data["eval_s"]),
        dict(data["versions"]),
    )


def curve_rows(results: dict[str, SideResult]) -> list[dict[str, Any]]:
    """One row per frame count at which any side evaluated: each side's team return there (None: none)."""
    by_side = {side: dict(r.evaluations) for side, r in results.items()}
    frames = sorted({f for evaluations in by_side.values() for f in evaluations})
    return [{"frames": f, **{side: by_side[side].get(f) for side in results}} for f in frames]


def _parser() -> argparse.ArgumentParser:
    parser = make_parser(
        "mcrs-bench-benchmarl",
        "Our QMIX beside BenchMARL's on VMAS navigation: team return by frames and wall s per 100k frames.",
        threads=1,
        quick="10-step episodes, 80 frames, 4 environments: a smoke test",
    )
    parser.add_argument("--sides", nargs="+", choices=SIDES, default=list(SIDES), help="which sides to run")
    parser.add_argument(
        "--benchmarl-python",
        default=DEFAULT_PYTHON,
        help=f"the Python of a virtual environment with benchmarl and vmas (default {DEFAULT_PYTHON})",
    )
    parser.add_argument("--frames", type=int, default=Settings.frames, help="frames (env steps) per side")
    parser.add_argument("--eval-interval", type=int, default=Settings.eval_interval, help="frames")
    parser.add_argument("--eval-episodes", type=int, default=Settings.eval_episodes)
    parser.add_argument("--seed", type=int, default=Settings.seed)
    return parser


def settings_from(args: argparse.Namespace) -> Settings:
    """The shared settings of a command line (``--quick``: :data:`QUICK`; the exploration anneals over a
    third of the frames unless that is what ``--quick`` sets)."""
    if args.quick:
        return Settings(seed=args.seed, threads=args.threads, **QUICK)
    return Settings(
        seed=args.seed,
        threads=args.threads,
        frames=args.frames,
        eval_interval=args.eval_interval,
        eval_episodes=args.eval_episodes,
        eps_anneal_frames=max(args.frames // 3, 1),
    )


def _validate(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    require_at_least(parser, args, 1, "frames", "eval_interval", "eval_episodes")
    require_at_least(parser, args, 0, "seed")
    problems = settings_from(args).problems()
    if problems:
        parser.error(problems[0])


def main(argv: Sequence[str] | None = None) -> int:
    return run_benchmark(_parser(), argv, _run, _validate)


def _run(args: argparse.Namespace, report: Report) -> None:
    s = settings_from(args)
    report.header("QMIX beside BenchMARL", details=f"VMAS {s.scenario}, ")
    print(
        f"{s.scenario_kwargs['n_agents']} agents, {s.max_steps}-step episodes, seed {s.seed}; {s.frames:,} frames "
        f"per side, {s.n_envs} environments per collection, {s.updates_per_batch} updates of "
        f"{s.batch_episodes} episodes ({s.batch_episodes * s.max_steps:,} transitions) after each; Adam "
        f"{s.lr:g}, gamma {s.gamma:g}, hidden {s.hidden}, mixer {s.mixing_embed_dim}; greedy evaluation of "
        f"{s.eval_episodes} episodes every {s.eval_interval:,} frames",
        flush=True,
    )
    report.arguments["settings"] = asdict(s)
    report.arguments["benchmarl_fields"] = benchmarl_fields(asdict(s))
    report.arguments["ours_overrides"] = ours_overrides(s)
    results: dict[str, SideResult] = {}
    for side in args.sides:
        print(f"\n{LABELS[side]}: training ... (load average {os.getloadavg()[0]:.2f})", flush=True)
        try:
            result = run_ours(s) if side == "ours" else run_benchmarl(s, args.benchmarl_python)
        # a side that fails is a finding of the comparison, recorded with its cause
        except Exception as error:
            result = SideResult(error=f"{type(error).__name__}: {error}")
        results[side] = result
        load = f"load average {os.getloadavg()[0]:.2f}"
        if result.error:
            print(f"  did not run: {result.error} ({load})", flush=True)
        else:
            print(f"  {result.frames:,} frames in {result.wall_s:.1f} s ({load})", flush=True)
        _record(report, side, result)
    rows = curve_rows(results)
    report.tables["curve"] = rows
    print(f"\nteam return of the greedy evaluation ({s.eval_episodes} episodes) by frames:")
    print(f"{'frames':>8} " + " ".join(f"{LABELS[side]:>30}" for side in results))
    for row in rows:
        cells = " ".join(f"{_cell(row[side]):>30}" for side in results)
        print(f"{row['frames']:>8,} {cells}")
    tail = f"last {TAIL:.0%} mean"
    print(
        f"\n{'side':<30} {'final return':>12} {tail:>13} {'s/100k frames':>14} {'with eval':>10} {'wall s':>8}"
    )
    for side, r in results.items():
        print(
            f"{LABELS[side]:<30} {_cell(r.final_return):>12} {_cell(r.tail_return()):>13} "
            f"{_cell(r.seconds_per(), '.0f'):>14} "
            f"{_cell(r.seconds_per(with_eval=True), '.0f'):>10} {_cell(r.wall_s, '.0f'):>8}"
        )
    if all(side in results and not results[side].error for side in SIDES):
        ratio = results["ours"].seconds_per() / results["benchmarl"].seconds_per()
        report.figure("time_ratio", ratio, "x", note="ours / BenchMARL, training wall s per frame")
        print(f"ours / BenchMARL, training wall clock per frame: {ratio:.2f}x")


def _record(report: Report, side: str, r: SideResult) -> None:
    """The side's figures (None and ``valid=False`` with the error when it did not run) and its row."""
    valid, note = not r.error, r.error
    report.figure(f"{side}.final_return", r.final_return, "team return", valid=valid, note=note)
    report.figure(
        f"{side}.tail_return",
        r.tail_return(),
        "team return",
        valid=valid,
        note=note or f"mean of the evaluations in the last {TAIL:.0%} of the frames",
    )
    report.figure(
        f"{side}.s_per_100k_frames", r.seconds_per(), "s", valid=valid, note=note or "without evaluation"
    )
    report.figure(
        f"{side}.s_per_100k_frames_with_eval", r.seconds_per(with_eval=True), "s", valid=valid, note=note
    )
    report.row(
        "sides", side=side, frames=r.frames, wall_s=_finite(r.wall_s), eval_s=_finite(r.eval_s),
        final_return=_finite(r.final_return), tail_return=_finite(r.tail_return()),
        error=r.error or None, **{f"version_{k}": v for k, v in r.versions.items()},
    )  # fmt: skip


def _installed(package: str) -> str:
    """The installed version of ``package`` ("?" when it is not installed as a distribution)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(package)
    except PackageNotFoundError:
        return "?"


def _finite(value: float) -> float | None:
    """None for NaN: the JSON has no NaN (a side that did not run has no clock)."""
    return None if value != value else value


def _cell(value: float | None, spec: str = ".2f") -> str:
    return "-" if value is None or value != value else format(value, spec)


if __name__ == "__main__":
    sys.exit(main())
