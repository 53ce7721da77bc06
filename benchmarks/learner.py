"""Learner benchmark (``mcrs-bench-learner``, ``python -m mcrs_benchmarks.learner``).

Why: the TorchRL stack (replay buffer, ``LossModule``, functional target parameters) must not make a
learner update much slower than the plain PyTorch a pymarl user would write, and a whole training run must
fit the design's time budget. This prints, at the pymarl preset (QMIX, 32-episode batches, RMSprop,
double Q, one-step targets), with PASS/FAIL:

* seconds per learner update of our :class:`~mcrs.experiment.training.learner.Learner` (a batch sampled from our
  TorchRL episode buffer, then ``Learner.update``) and of the plain-PyTorch reference learner
  (:mod:`mcrs_benchmarks.reference_learner`: same networks, no TorchRL, no tensordict); goal: ours <= 1.15x
  the reference (JSON figure ``<map>.update_ratio``);
* env-steps/s of the real training loop (:mod:`mcrs_benchmarks.loop`) in steady state, and the hours it
  extrapolates to for 2M env steps; goal on map20: <= 1.25 h (``map20.hours``);
* with ``--launcher-steps``, two 1-thread runs side by side against one 2-thread run (``launcher.ratio``).

Fairness: the reference starts from our learner's weights (state dicts), and the two losses are checked
once to agree (to 1e-5 relative, ``<map>.loss_rel_diff``) on the same batch, before and after one update of
each; a reference that computed something else would not be a reference. The two learners are timed alternately (A/B, then B/A)
in the same process so that machine drift hits both, and the ratio is the median of the per-pair ratios.
The replay holds synthetic but valid episodes in the episode layout (random observations and states,
random masks with at least one allowed action, actions drawn among the allowed ones): the cost of an
update does not depend on the values.
"""

from __future__ import annotations

import argparse
import gc
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from mcrs_benchmarks.common import compose_config, load_average, synthetic_episodes
from mcrs_benchmarks.harness import Figure, Goal, Report, make_parser, require_at_least, run_benchmark
from mcrs_benchmarks.loop import GOAL_STEPS, LoopResult, collector_step_seconds, launcher_rates, measure_loop
from mcrs_benchmarks.reference_learner import (
    AGREE_RTOL,
    Agreement,
    ReferenceLearner,
    ReferenceReplay,
    as_plain,
    check_agreement,
)

from mcrs.env.config import SCENARIOS, EnvConfig, from_mapping

GOAL_RATIO = 1.15  # ours / reference, seconds per update
GOAL_MAP = "map20"
GOAL_HOURS = 1.25  # wall-clock for GOAL_STEPS env steps on GOAL_MAP
WARMUP = 3  # untimed updates of each learner before the timed ones
REPLAY_EPISODES = 256  # synthetic episodes in each replay (sampling cost hardly depends on it)
DEFAULT_UPDATES = 30
DEFAULT_LOOP_STEPS = 20_000
QUICK_REPLAY_EPISODES = 16
QUICK_NOTE = "\n--quick: 4-episode batches of 6-step episodes instead, goals not judged"
QUICK_UPDATES = 3


@dataclass
class UpdateTimes:
    """Medians over the timed updates, seconds; ``ratio`` is the median of per-pair ours/reference."""

    ours_sample: float
    ours_update: float
    ref_sample: float
    ref_update: float
    ratio: float
    pairs: int

    @property
    def ours(self) -> float:
        return self.ours_sample + self.ours_update

    @property
    def ref(self) -> float:
        return self.ref_sample + self.ref_update


def _timed(step: Callable[[], Any], update: Callable[[Any], Any]) -> tuple[float, float]:
    start = time.perf_counter()
    batch = step()
    mid = time.perf_counter()
    update(batch)
    return mid - start, time.perf_counter() - mid


def measure_updates(map_name: str, quick: bool, updates: int) -> tuple[EnvConfig, Agreement, UpdateTimes]:
    """Build both learners from the same weights, check their losses agree, then time them alternately."""
    from mcrs.experiment.training.learner import Learner
    from mcrs.experiment.training.replay import make_episode_buffer

    cfg = compose_config(map_name, quick)
    env_config = from_mapping(cfg.env)
    n_episodes = QUICK_REPLAY_EPISODES if quick else REPLAY_EPISODES
    batch_size = int(cfg.train.batch_episodes)
    torch.manual_seed(0)
    learner = Learner(cfg.algo, cfg.model, cfg.train, env_config, torch.device("cpu"))
    reference = ReferenceLearner(cfg, env_config)
    reference.load_weights(
        {
            **learner.weights(),
            "target_agent": learner.loss.target_agent_network_params.state_dict(),
            "target_mixer": learner.loss.target_mixer_params.state_dict(),
        }
    )
    episodes = synthetic_episodes(n_episodes, env_config, torch.Generator().manual_seed(0))
    replay = make_episode_buffer(n_episodes, batch_size)
    replay.extend(episodes)
    ref_replay = ReferenceReplay(as_plain(episodes), batch_size)
    del episodes

    agreement = check_agreement(learner, reference, replay)

    def ours() -> tuple[float, float]:
        return _timed(replay.sample, lambda batch: learner.update(batch, 0))

    def ref() -> tuple[float, float]:
        return _timed(ref_replay.sample, reference.update)

    gc.collect()
    samples: dict[str, list[tuple[float, float]]] = {"ours": [], "ref": []}
    for i in range(WARMUP + updates):
        order = (("ours", ours), ("ref", ref)) if i % 2 == 0 else (("ref", ref), ("ours", ours))
        for name, run in order:
            result = run()
            if i >= WARMUP:
                samples[name].append(result)
    o, r = samples["ours"], samples["ref"]
    times = UpdateTimes(
        ours_sample=statistics.median(s for s, _ in o),
        ours_update=statistics.median(u for _, u in o),
        ref_sample=statistics.median(s for s, _ in r),
        ref_update=statistics.median(u for _, u in r),
        ratio=statistics.median(sum(a) / sum(b) for a, b in zip(o, r, strict=True)),
        pairs=updates,
    )
    return env_config, agreement, times


def _parser() -> argparse.ArgumentParser:
    parser = make_parser(
        "mcrs-bench-learner",
        "Seconds per learner update (ours vs a plain-PyTorch reference) and training-loop "
        "throughput at the pymarl preset, with goals.",
        quick="tiny episodes and batches: a smoke test",
    )
    parser.add_argument("--maps", nargs="+", choices=SCENARIOS, default=["map10", "map20"], help="presets")
    parser.add_argument(
        "--updates", type=int, default=None, help=f"timed updates per learner (default {DEFAULT_UPDATES})"
    )
    parser.add_argument(
        "--loop-steps",
        type=int,
        default=None,
        help=f"env steps of the training-loop run per map (default {DEFAULT_LOOP_STEPS:,}; 0 skips it)",
    )
    parser.add_argument(
        "--launcher-steps",
        type=int,
        default=0,
        help="env steps of each run of the launcher comparison (one 2-thread run, then two 1-thread runs "
        "side by side) on the first map; 0 skips it",
    )
    return parser


def _validate(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    if args.updates is None:
        args.updates = QUICK_UPDATES if args.quick else DEFAULT_UPDATES
    if args.loop_steps is None:
        args.loop_steps = 1 if args.quick else DEFAULT_LOOP_STEPS  # --quick: the 4-batch minimum
    require_at_least(parser, args, 1, "updates")
    require_at_least(parser, args, 0, "loop_steps", "launcher_steps")


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark and print the update table, the ratios, the loop figures and the goals."""
    return run_benchmark(_parser(), argv, _run, _validate)


def _run(args: argparse.Namespace, report: Report) -> None:
    judged = not args.quick
    not_judged = "" if judged else "--quick"
    goals: list[Figure] = []
    report.header("learner benchmark")
    print(
        "preset pymarl: QMIX (2-layer hypernets), 32-episode batches, RMSprop lr 5e-4, double Q, one-step "
        f"targets, grad clip 10{QUICK_NOTE if args.quick else ''}\n"
        f"update rows: median of {args.updates} timed updates (sample a batch + gradient step) after {WARMUP} "
        f"warm-up, ours and reference alternated; replay of "
        f"{QUICK_REPLAY_EPISODES if args.quick else REPLAY_EPISODES} synthetic episodes each",
        flush=True,
    )
    for name in args.maps:
        env_config, agreement, times = measure_updates(name, args.quick, args.updates)
        _print_updates(report, name, env_config, agreement, times)
        ratio = report.figure(
            f"{name}.update_ratio", times.ratio, "x", Goal("<=", GOAL_RATIO), not_judged=not_judged,
            valid=agreement.agree, note=f"ours / reference per update, median of {times.pairs} pairs",
        )  # fmt: skip
        print(
            f"ratio {name}: ours / reference = {times.ratio:.2f}x per update (median of {times.pairs} "
            f"interleaved pairs; goal <= {GOAL_RATIO:g}x: {ratio.verdict})",
            flush=True,
        )
        goals.append(ratio)

    if args.loop_steps:
        print(
            "\ncollector step (env + recurrent policy + exploration), 1 env vs 32 envs at once:", flush=True
        )
        for name in args.maps:
            env_config = from_mapping(compose_config(name, args.quick).env)
            one, many = (collector_step_seconds(env_config, e, 1 if args.quick else 3) for e in (1, 32))
            report.row("collector", map=name, ms_per_step_1_env=one * 1e3, ms_per_step_32_envs=many * 1e3)
            print(
                f"{name:<6} 1 env {one * 1e3:.2f} ms/step, 32 envs {many * 1e3:.2f} ms/step "
                f"({many / 32 * 1e3:.3f} ms per env step)",
                flush=True,
            )
        print(
            "\ntraining loop (the real Experiment, pymarl preset, csv logger, no progress bar, no checkpoints): "
            "steady state from the end of the first collector batch to the end of the last;\n"
            "evaluation only at the start and end of the run, timed on its own and added back at the "
            "preset's interval; checkpoints (every 100,000 steps, with the replay) not included",
            flush=True,
        )
        print(
            f"{'map':<6} {'window steps':>12} {'env-steps/s':>12} {'s/update':>9} {'eval s':>7} "
            f"{'2M h (loop)':>11} {'2M h (+eval)':>12}"
        )
        for name in args.maps:
            hours = _loop_row(
                report, name, measure_loop(name, args.quick, args.loop_steps, args.threads), judged
            )
            if name == GOAL_MAP:
                goals.append(hours)
    if args.launcher_steps:
        name = args.maps[0]
        print(
            f"\nlauncher ({name}, the real Experiment as above, each run in its own process): one run with 2 torch "
            "threads alone, then two runs with 1 thread each side by side",
            flush=True,
        )
        one, pair = launcher_rates(name, args.quick, args.launcher_steps)
        report.figure("launcher.one_2_thread_env_steps_per_s", one, "env-steps/s")
        report.figure("launcher.two_1_thread_env_steps_per_s", sum(pair), "env-steps/s", note=f"{pair}")
        ratio = report.figure(
            "launcher.ratio", sum(pair) / one, "x", note="two 1-thread runs / one 2-thread run"
        )
        print(
            f"one 2-thread run: {one:,.0f} env-steps/s; two 1-thread runs: {pair[0]:,.0f} + {pair[1]:,.0f} = "
            f"{sum(pair):,.0f} env-steps/s (load average {load_average()})\n"
            f"two 1-thread runs vs one 2-thread run: {ratio.value:.2f}x (aggregate env-steps/s; above 1: "
            "the local2 launcher's two 1-thread runs use the cores better)",
            flush=True,
        )
    if judged:
        if f"{GOAL_MAP}.hours" not in report.figures:
            goals.append(
                report.figure(
                    f"{GOAL_MAP}.hours", None, "h", Goal("<=", GOAL_HOURS), note="loop not measured"
                )
            )
        _print_goals(goals)


def _print_updates(
    report: Report, name: str, env_config: EnvConfig, agreement: Agreement, times: UpdateTimes
) -> None:
    """The agreement line and the two update rows of one map."""
    diff = report.figure(
        f"{name}.loss_rel_diff", max(agreement.rel_diffs), "", Goal("<=", AGREE_RTOL),
        note="ours vs reference loss, before and after one update; above the goal the comparison is void",
    )  # fmt: skip
    diffs = ", ".join(f"{d:.1e}" for d in agreement.rel_diffs)
    print(
        f"\n{name}: {env_config.n_uavs} agents, T={env_config.max_steps}, obs {env_config.obs_dim}, "
        f"state {env_config.state_dim}\n"
        f"losses agree: {'yes' if diff.passed else 'no'} (ours {agreement.ours[0]:.6g} / "
        f"{agreement.ours[1]:.6g}, reference {agreement.reference[0]:.6g} / {agreement.reference[1]:.6g} "
        f"before / after one update; relative differences {diffs}; tolerance {AGREE_RTOL:g})",
        flush=True,
    )
    print(f"{'map':<6} {'learner':<10} {'sample ms':>10} {'update ms':>10} {'total ms':>10}")
    for label, sample, update in (
        ("ours", times.ours_sample, times.ours_update),
        ("reference", times.ref_sample, times.ref_update),
    ):
        report.figure(
            f"{name}.update_ms.{label}", (sample + update) * 1e3, "ms", note="sample + update, median"
        )
        report.row("updates", map=name, learner=label, sample_ms=sample * 1e3, update_ms=update * 1e3)
        print(
            f"{name:<6} {label:<10} {sample * 1e3:>10.2f} {update * 1e3:>10.2f} {(sample + update) * 1e3:>10.2f}"
        )


def _loop_row(report: Report, name: str, r: LoopResult, judged: bool) -> Figure:
    """Print and record one training-loop row; return the map's whole-run hours figure."""
    per_update = r.update_seconds / r.updates if r.updates else float("nan")
    hours = r.hours(GOAL_STEPS, False)
    report.figure(f"{name}.loop_env_steps_per_s", r.env_steps_per_s, "env-steps/s")
    report.row(
        "loop", map=name, window_steps=r.env_steps, env_steps_per_s=r.env_steps_per_s, seconds_per_update=per_update,
        eval_seconds=r.eval_seconds, hours_loop=hours, hours=r.hours(GOAL_STEPS, True), run_steps=r.total_steps,
        updates=r.updates, wall_seconds=r.wall_seconds, eval_episodes=r.eval_episodes, eval_interval=r.eval_interval,
    )  # fmt: skip
    fig = report.figure(
        f"{name}.hours", r.hours(GOAL_STEPS, True), "h", Goal("<=", GOAL_HOURS) if name == GOAL_MAP else None,
        not_judged="" if judged or name != GOAL_MAP else "--quick",
        note=f"loop {hours:.2f} h + evaluation every {r.eval_interval:,} steps; checkpoints not included",
    )  # fmt: skip
    print(
        f"{name:<6} {r.env_steps:>12,} {r.env_steps_per_s:>12,.0f} {per_update:>9.4f} "
        f"{r.eval_seconds:>7.2f} {hours:>11.2f} {fig.value:>12.2f}   "
        f"(run of {r.total_steps:,} steps, {r.updates} updates in the window, {r.wall_seconds:.0f} s wall; "
        f"eval: {r.eval_episodes} episodes every {r.eval_interval:,} steps)",
        flush=True,
    )
    return fig


def _print_goals(goals: list[Figure]) -> None:
    """The goals section: the same lines the benchmark always printed, from the recorded figures."""
    print("\ngoals:", flush=True)
    for fig in goals:
        name = fig.name.split(".")[0]
        if fig.name.endswith("update_ratio"):
            note = "" if fig.valid else " (losses disagree: the comparison is void)"
            line = f"{name} update ours / reference <= {GOAL_RATIO:g}x: {fig.value:.2f}x {fig.verdict}{note}"
        elif fig.value is None:
            line = f"{name} {GOAL_STEPS / 1e6:g}M env steps <= {GOAL_HOURS:g} h: n/a (loop not measured)"
        else:
            line = f"{name} {GOAL_STEPS / 1e6:g}M env steps <= {GOAL_HOURS:g} h: {fig.value:.2f} h {fig.verdict} ({fig.note})"
        print(f"  {line}", flush=True)


if __name__ == "__main__":
    raise SystemExit(main())
