"""Environment throughput and memory benchmark (``mcrs-bench-env``, ``python -m mcrs_benchmarks.env_throughput``).

Why: training speed is bounded by how fast the batched simulator steps, and the design promises three
figures, printed here next to the measurements with PASS/FAIL:

* map20 with 1024 parallel environments: >= 50,000 env-steps/s (500,000 agent-steps/s) through ``MCRSEnv``;
* >= 100x the classic loop that steps one PettingZoo environment at a time (``MCRSParallelEnv``);
* 10,000 parallel map20 environments fit in <= 2 GiB.

In the JSON (:mod:`mcrs_benchmarks.harness`): figures ``goal_env_steps_per_s``, ``<map>.ratio_to_pettingzoo``,
``memory_projected_gib``, ``memory_measured_gib``; every row in the table ``throughput``.

``--env-override KEY=VALUE ...`` (or ``--variants``: delay, bandwidth and moving targets of the presets
``map20_delay``, ``map20_bandwidth`` and ``map20_dynamic`` at once) times every MCRSEnv row a second
time with those scenario fields, right after the paper's row, and prints the ratio of the two; the goal
figure ``goal_variant_env_steps_per_s`` holds the variant's map20 @1024 row (>= 50,000 env-steps/s), judged
only when every override is one of the variants' fields (other fields, such as the shields, have no goal).
Each row also gives env-steps per CPU-second of this process (``time.process_time``), a figure that
other processes on a loaded machine disturb less than the wall clock.

The TorchRL path is timed the way a collector drives it: ``env.step_and_maybe_reset(td)`` in a loop, with
uniformly random *allowed* actions drawn for all environments at once from ``("agents", "action_mask")``.
Drawing the actions is inside the timed loop, as a policy would be. The PettingZoo reference steps one
environment at a time on the CPU (one torch thread, its fastest setting) with random allowed actions,
resetting at episode end. Each row is the fastest of ``REPEATS`` timed runs after a warm-up, because
other processes on a shared machine only ever slow a run down; a run is a whole number of episodes, so
the cost of resets is always included.
"""

from __future__ import annotations

import argparse
import gc
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from mcrs_benchmarks.common import pass_fail
from mcrs_benchmarks.harness import Goal, Report, make_parser, require_at_least, run_benchmark

from mcrs.env.config import SCENARIOS, scenario
from mcrs.env.core import MCRSCore
from mcrs.env.pettingzoo_env import MCRSParallelEnv
from mcrs.env.torchrl_env import MCRSEnv
from mcrs.policies import RandomPolicy

GOAL_MAP = "map20"
GOAL_NUM_ENVS = 1024
GOAL_ENV_STEPS = 50_000
GOAL_AGENT_STEPS = 500_000
GOAL_RATIO = 100.0
MEMORY_NUM_ENVS = 10_000
GOAL_GIB = 2.0
GIB = 2**30
REPEATS = 3  # timed runs per row; the fastest is reported
#: ``--variants``: the three variant presets' fields at once (mcrs/conf/env/map20_*.yaml).
VARIANTS = {
    "comm_delay": 3,
    "comm_budget": 4,
    "target_motion": "random_walk",
    "target_move_prob": 0.05,
    "evidence_decay": 0.02,
}


@dataclass
class Row:
    """One measured throughput figure."""

    map_name: str
    path: str  # "MCRSEnv" or "PettingZoo"
    num_envs: int
    steps: int  # environment steps timed (summed over the batch)
    seconds: float
    n_uavs: int
    cpu_seconds: float | None = None  # CPU time of this process over the same run

    @property
    def env_steps_per_cpu_s(self) -> float | None:
        return None if not self.cpu_seconds else self.steps / self.cpu_seconds

    @property
    def env_steps(self) -> float:
        return self.steps / self.seconds

    @property
    def agent_steps(self) -> float:
        return self.env_steps * self.n_uavs


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _calibrated_run(
    run: Callable[[int], None], seconds: float, device: torch.device, episode_steps: int
) -> tuple[int, float, float]:
    """Warm up (which also measures the rate), then time ``REPEATS`` runs of a fixed number of steps that
    together last about ``seconds`` (one run when an episode is longer); return (steps, elapsed) of the
    fastest run, and the CPU time of this process during that run.

    The fastest run is the figure least disturbed by other processes on a shared machine (as ``timeit``
    recommends). Each run is a whole number of episodes long, so that every run pays for the same number
    of resets (all environments of a batch end together) and picking the fastest cannot skip them.
    """
    warm_steps, warm_time, budget = 0, 0.0, min(0.5, max(seconds / 4, 0.05))
    while warm_steps < 3 or warm_time < budget:
        start = time.perf_counter()
        run(1)
        _synchronize(device)
        warm_time += time.perf_counter() - start
        warm_steps += 1
    episode_seconds = episode_steps * warm_time / warm_steps
    # Runs of whole episodes: when one episode alone takes longer than the budget, a single run.
    repeats = REPEATS if episode_seconds <= seconds else 1
    n_steps = episode_steps * max(1, round(seconds / repeats / episode_seconds))
    best, best_cpu = math.inf, math.inf
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        run(n_steps)
        _synchronize(device)
        elapsed = time.perf_counter() - start
        if elapsed < best:
            best, best_cpu = elapsed, time.process_time() - start_cpu
    return n_steps, best, best_cpu


def measure_torchrl(
    map_name: str,
    num_envs: int,
    seconds: float,
    device: torch.device,
    overrides: dict[str, Any] | None = None,
) -> Row:
    """Env-steps/s of ``MCRSEnv`` driven by ``step_and_maybe_reset``, as a TorchRL collector does;
    ``overrides`` are scenario fields (e.g. the variants beyond the paper)."""
    env = MCRSEnv(map_name, device=device, num_envs=num_envs, **(overrides or {}))
    env.set_seed(0)
    policy = RandomPolicy(env.config, seed=0)  # uniform over allowed moves, batched
    td = env.reset()

    def run(n: int) -> None:
        nonlocal td
        for _ in range(n):
            _, td = env.step_and_maybe_reset(policy(td))

    n_steps, elapsed, cpu = _calibrated_run(run, seconds, device, env.config.max_steps)
    path = "MCRSEnv+var" if overrides else "MCRSEnv"
    return Row(map_name, path, num_envs, n_steps * num_envs, elapsed, env.config.n_uavs, cpu)


def measure_pettingzoo(map_name: str, seconds: float) -> Row:
    """Env-steps/s of the classic loop: one ``MCRSParallelEnv`` on the CPU (one torch thread), stepped
    through its dict API."""
    env = MCRSParallelEnv(map_name)
    rng = np.random.default_rng(0)
    observations, _ = env.reset(seed=0)

    def run(n: int) -> None:
        nonlocal observations
        for _ in range(n):
            agents = env.agents
            mask = np.stack([observations[agent]["action_mask"] for agent in agents])
            noise = rng.random(mask.shape)
            noise[mask == 0] = -1.0
            observations, *_ = env.step(dict(zip(agents, noise.argmax(1).tolist(), strict=True)))
            if not env.agents:
                observations, _ = env.reset()

    # One intra-op thread: a single small environment gains nothing from more, and on a busy machine
    # their synchronisation makes every tiny op wait for a descheduled thread. The reference is the
    # loop at its best, so that the ratio is not flattered.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        n_steps, elapsed, cpu = _calibrated_run(run, seconds, torch.device("cpu"), env.config.max_steps)
    finally:
        torch.set_num_threads(threads)
    return Row(map_name, "PettingZoo", 1, n_steps, elapsed, env.config.n_uavs, cpu)


def state_bytes_per_env(map_name: str) -> float:
    """Episode-state bytes per environment (``core.state_nbytes() / num_envs``); exact, it is linear in E."""
    num_envs = 8
    return MCRSCore(scenario(map_name, num_envs=num_envs), device="cpu").state_nbytes() / num_envs


def resident_bytes() -> int | None:
    """This process's resident memory (VmRSS of /proc/self/status), or None where there is no /proc."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        return None
    return None


def measure_memory(map_name: str, num_envs: int, device: torch.device, steps: int = 3) -> int | None:
    """Memory added by building, resetting and stepping ``num_envs`` environments (VmRSS, or CUDA bytes)."""

    def used() -> int | None:
        if device.type == "cuda":
            _synchronize(device)
            return torch.cuda.memory_allocated(device)
        return resident_bytes()

    gc.collect()
    before = used()
    if before is None:
        return None
    env = MCRSEnv(map_name, device=device, num_envs=num_envs)
    policy = RandomPolicy(env.config, seed=0)
    td = env.reset()
    for _ in range(steps):
        _, td = env.step_and_maybe_reset(policy(td))
    after = used()
    del env, td
    gc.collect()
    return None if after is None else after - before


def _parser() -> argparse.ArgumentParser:
    parser = make_parser(
        "mcrs-bench-env",
        "Throughput (env-steps/s, agent-steps/s) and memory of the MCRS environment, with goals.",
    )
    parser.add_argument("--maps", nargs="+", choices=SCENARIOS, default=list(SCENARIOS), help="presets")
    parser.add_argument(
        "--num-envs", nargs="+", type=int, default=[1, 64, GOAL_NUM_ENVS], help="batch sizes of MCRSEnv"
    )
    parser.add_argument("--seconds", type=float, default=2.0, help="timed seconds per MCRSEnv row")
    parser.add_argument("--device", default="cpu", help="torch device of MCRSEnv (PettingZoo runs on cpu)")
    parser.add_argument(
        "--skip-memory", action="store_true", help=f"skip the {MEMORY_NUM_ENVS}-environment memory check"
    )
    parser.add_argument(
        "--env-override",
        nargs="+",
        default=[],
        metavar="KEY=VALUE",
        help="scenario fields (e.g. comm_delay=2 comm_budget=4): each MCRSEnv row is timed again with them",
    )
    parser.add_argument(
        "--variants",
        action="store_true",
        help="time every MCRSEnv row again with delay, bandwidth and moving targets on: "
        + " ".join(f"{k}={v}" for k, v in VARIANTS.items()),
    )
    return parser


def _overrides(parser: argparse.ArgumentParser, args: argparse.Namespace) -> dict[str, Any]:
    """The scenario fields of ``--variants`` and ``--env-override`` (the latter win), checked on each map."""
    import yaml

    values: dict[str, Any] = dict(VARIANTS) if args.variants else {}
    for item in args.env_override:
        key, sep, text = item.partition("=")
        if not sep or not key:
            parser.error(f"--env-override takes KEY=VALUE items (e.g. comm_delay=2), got {item!r}")
        values[key] = yaml.safe_load(text)
    for name in args.maps:
        try:
            scenario(name, **values)
        except ValueError as error:
            parser.error(f"--env-override on {name}: {' '.join(str(error).split())}")
    return values


def _validate(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    require_at_least(parser, args, 1, "num_envs")
    if args.seconds <= 0:
        parser.error(f"--seconds must be > 0, got {args.seconds}")
    args.overrides = _overrides(parser, args)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark and print the table, the PettingZoo ratios, memory and the goals."""
    return run_benchmark(_parser(), argv, _run, _validate)


def _run(args: argparse.Namespace, report: Report) -> None:
    """Memory first, then the throughput rows, the ratios, and the goals with PASS/FAIL."""
    device = torch.device(args.device)
    num_envs_list = sorted(set(args.num_envs))
    largest = num_envs_list[-1]
    goals: list[str] = []
    report.header("environment benchmark", device=str(device))
    print(
        f"each row: best of up to {REPEATS} timed runs of whole episodes, ~{args.seconds:g} s in all per MCRSEnv row; "
        "PettingZoo loop: one env at a time, 1 torch thread",
        flush=True,
    )

    # Memory first, while the process is small, so that the resident-memory difference is not hidden by
    # memory that earlier rows freed but the allocator kept.
    if not args.skip_memory:
        print("\nmemory (episode state held by the core, core.state_nbytes() / num_envs):", flush=True)
        per_env = {name: state_bytes_per_env(name) for name in SCENARIOS}
        for name, nbytes in per_env.items():
            report.figure(f"{name}.state_bytes_per_env", nbytes, "B")
            print(f"  {name:<6} {nbytes:>10,.0f} bytes/env", flush=True)
        memory_goal = Goal("<=", GOAL_GIB)
        projected = report.figure(
            "memory_projected_gib", per_env[GOAL_MAP] * MEMORY_NUM_ENVS / GIB, "GiB", memory_goal,
            note=f"{MEMORY_NUM_ENVS:,} {GOAL_MAP} envs, core.state_nbytes()",
        )  # fmt: skip
        print(f"  projection, {MEMORY_NUM_ENVS:,} {GOAL_MAP} envs: {projected.value:.3f} GiB", flush=True)
        measured = measure_memory(GOAL_MAP, MEMORY_NUM_ENVS, device)
        what = "CUDA memory_allocated" if device.type == "cuda" else "VmRSS"
        measured_fig = report.figure(
            "memory_measured_gib", None if measured is None else measured / GIB, "GiB", memory_goal,
            not_judged="" if measured is not None else f"{what} not readable here",
            note=f"{MEMORY_NUM_ENVS:,} {GOAL_MAP} envs built, reset and stepped 3 times: {what} growth",
        )  # fmt: skip
        if measured is None:
            print(f"  measured: n/a ({what} not readable here)", flush=True)
            measured_text = "measured n/a"
        else:
            print(
                f"  measured, {GOAL_MAP} MCRSEnv num_envs={MEMORY_NUM_ENVS:,} built, reset and stepped 3 times: "
                f"{what} {measured / GIB:+.3f} GiB",
                flush=True,
            )
            measured_text = f"measured {measured / GIB:+.3f} GiB {measured_fig.verdict}"
        goals.append(
            f"{MEMORY_NUM_ENVS:,} {GOAL_MAP} envs <= {GOAL_GIB:g} GiB: projected {projected.value:.3f} GiB "
            f"{projected.verdict}; {measured_text}"
        )

    overrides = args.overrides
    if overrides:
        print("variant rows (MCRSEnv+var): " + " ".join(f"{k}={v}" for k, v in overrides.items()), flush=True)
    print(
        f"\n{'map':<6} {'path':<11} {'num_envs':>8} {'env-steps/s':>13} {'agent-steps/s':>14} "
        f"{'env-steps/cpu-s':>15}",
        flush=True,
    )
    rows: dict[tuple[str, str, int], Row] = {}
    for name in args.maps:
        for num_envs in num_envs_list:
            rows[name, "MCRSEnv", num_envs] = row = measure_torchrl(name, num_envs, args.seconds, device)
            _print_row(row, report)
            if overrides:
                variant = measure_torchrl(name, num_envs, args.seconds, device, overrides)
                rows[name, "MCRSEnv+var", num_envs] = variant
                _print_row(variant, report, baseline=row)
        rows[name, "PettingZoo", 1] = row = measure_pettingzoo(name, max(args.seconds / 2, 0.1))
        _print_row(row, report)

    print(flush=True)
    judged = largest == GOAL_NUM_ENVS
    for name in args.maps:
        ratio = report.figure(
            f"{name}.ratio_to_pettingzoo",
            rows[name, "MCRSEnv", largest].env_steps / rows[name, "PettingZoo", 1].env_steps,
            "x",
            Goal(">=", GOAL_RATIO),
            not_judged="" if judged else f"judged at num_envs {GOAL_NUM_ENVS}",
            note=f"MCRSEnv@{largest} / PettingZoo loop",
        )
        note = f"goal >= {GOAL_RATIO:g}x: {ratio.verdict}" if judged else f"goal judged at {GOAL_NUM_ENVS}"
        print(
            f"ratio {name}: MCRSEnv@{largest} / PettingZoo loop = {ratio.value:,.1f}x  ({note})", flush=True
        )
        if judged:
            goals.append(
                f"{name} MCRSEnv@{largest} >= {GOAL_RATIO:g}x PettingZoo loop: {ratio.value:,.1f}x {ratio.verdict}"
            )

    goal_row = rows.get((GOAL_MAP, "MCRSEnv", GOAL_NUM_ENVS))
    env_fig = report.figure(
        "goal_env_steps_per_s", None if goal_row is None else goal_row.env_steps, "env-steps/s",
        Goal(">=", GOAL_ENV_STEPS), not_judged="" if goal_row is not None else "not measured",
        note=f"{GOAL_MAP} MCRSEnv@{GOAL_NUM_ENVS}",
    )  # fmt: skip
    agent_fig = report.figure(
        "goal_agent_steps_per_s", None if goal_row is None else goal_row.agent_steps, "agent-steps/s",
        Goal(">=", GOAL_AGENT_STEPS), not_judged="" if goal_row is not None else "not measured",
        note=f"{GOAL_MAP} MCRSEnv@{GOAL_NUM_ENVS}",
    )  # fmt: skip
    if goal_row is None:
        goals.insert(0, f"{GOAL_MAP} @{GOAL_NUM_ENVS} >= {GOAL_ENV_STEPS:,} env-steps/s: n/a (not measured)")
    else:
        ok = bool(env_fig.passed and agent_fig.passed)
        goals.insert(
            0,
            f"{GOAL_MAP} @{GOAL_NUM_ENVS} >= {GOAL_ENV_STEPS:,} env-steps/s ({GOAL_AGENT_STEPS:,} agent-steps/s): "
            f"{goal_row.env_steps:,.0f} env-steps/s, {goal_row.agent_steps:,.0f} agent-steps/s {pass_fail(ok)}",
        )
    if overrides:
        variant_row = rows.get((GOAL_MAP, "MCRSEnv+var", GOAL_NUM_ENVS))
        fig = report.figure(
            "goal_variant_env_steps_per_s", None if variant_row is None else variant_row.env_steps,
            "env-steps/s", Goal(">=", GOAL_ENV_STEPS), not_judged=_variant_goal_not_judged(variant_row, overrides),
            note=f"{GOAL_MAP} MCRSEnv@{GOAL_NUM_ENVS} with " + " ".join(f"{k}={v}" for k, v in overrides.items()),
        )  # fmt: skip
        if variant_row is not None:
            paper = rows[GOAL_MAP, "MCRSEnv", GOAL_NUM_ENVS]
            ratio = variant_row.env_steps / paper.env_steps
            report.figure("variant_ratio_to_paper", ratio, "x", note="wall clock, same run")
            goals.append(
                f"{GOAL_MAP} @{GOAL_NUM_ENVS} with the variants >= {GOAL_ENV_STEPS:,} env-steps/s: "
                f"{variant_row.env_steps:,.0f} env-steps/s {fig.verdict} ({ratio:.2f}x the paper's row, "
                f"{paper.env_steps:,.0f})"
            )
    print("\ngoals:", flush=True)
    for line in goals:
        print(f"  {line}", flush=True)


def _variant_goal_not_judged(variant_row: Row | None, overrides: dict[str, Any]) -> str:
    """Why the variants' goal is not judged on these rows, or "": it is the goal of the variants' fields
    (delay, bandwidth, moving targets, decay); other fields (a shield, ``far_view``) have none."""
    if variant_row is None:
        return "not measured"
    others = [k for k in overrides if k not in VARIANTS]
    return f"no goal with {', '.join(others)}: the goal is the variants'" if others else ""


def _print_row(row: Row, report: Report, baseline: Row | None = None) -> None:
    """One table row; a variant row also gives its ratio to the paper's row ``baseline`` (wall, CPU)."""
    ratios: dict[str, float | None] = {}
    if baseline is not None:
        cpu = row.env_steps_per_cpu_s, baseline.env_steps_per_cpu_s
        ratios = {
            "ratio_to_paper": row.env_steps / baseline.env_steps,
            "cpu_ratio_to_paper": cpu[0] / cpu[1] if cpu[0] and cpu[1] else None,
        }
    report.row(
        "throughput", map=row.map_name, path=row.path, num_envs=row.num_envs, steps=row.steps,
        seconds=row.seconds, env_steps_per_s=row.env_steps, agent_steps_per_s=row.agent_steps,
        cpu_seconds=row.cpu_seconds, env_steps_per_cpu_s=row.env_steps_per_cpu_s, **ratios,
    )  # fmt: skip
    per_cpu = row.env_steps_per_cpu_s
    text = (
        f"{row.map_name:<6} {row.path:<11} {row.num_envs:>8} {row.env_steps:>13,.0f} {row.agent_steps:>14,.0f} "
        f"{'n/a' if per_cpu is None else f'{per_cpu:,.0f}':>15}"
    )
    if baseline is not None:
        cpu_ratio = ratios["cpu_ratio_to_paper"]
        text += f"  x{ratios['ratio_to_paper']:.2f} of the paper's row (CPU time: " + (
            "n/a)" if cpu_ratio is None else f"x{cpu_ratio:.2f})"
        )
    print(text, flush=True)


if __name__ == "__main__":
    raise SystemExit(main())
