"""Timing of the real training loop, shared by ``mcrs-bench-learner`` and ``mcrs-bench-overhead``.

Why: a whole run's wall clock is what a user waits for, and it is more than the learner update: the
collector, logging and evaluation all count. :func:`measure_loop` runs the real
:class:`~mcrs.experiment.training.trainer.Experiment` and times its steady state; :func:`launcher_rates` compares one
2-thread run with two 1-thread runs side by side (how a sweep should share two cores);
:func:`collector_step_seconds` times collection alone.
"""

from __future__ import annotations

import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from mcrs_benchmarks.common import compose_config

from mcrs.env.config import EnvConfig
from mcrs.env.core import N_ACTIONS

GOAL_STEPS = 2_000_000  # the length of a whole run the loop's rate is extrapolated to
NEVER = 10**12  # an interval the short loop run never reaches


@dataclass
class LoopResult:
    """The training loop between the end of its first collector batch and the end of its last one."""

    map_name: str
    env_steps: int  # in the steady-state window
    seconds: float
    updates: int
    update_seconds: float  # replay sampling + Learner.update, inside the window
    eval_seconds: float  # one evaluation (the last one), timed separately
    eval_episodes: int
    eval_interval: int  # the preset's, used for the extrapolation
    total_steps: int  # the whole run
    wall_seconds: float  # the whole run: construction, evaluations, final save

    @property
    def env_steps_per_s(self) -> float:
        return self.env_steps / self.seconds

    def hours(self, steps: int, with_eval: bool) -> float:
        evals = steps / self.eval_interval * self.eval_seconds if with_eval else 0.0
        return (steps / self.env_steps_per_s + evals) / 3600


def measure_loop(
    map_name: str, quick: bool, loop_steps: int, threads: int, algo: str = "qmix", extra: Sequence[str] = ()
) -> LoopResult:
    """Run the real :class:`Experiment` and time its steady state from its own counters.

    The run evaluates only at its start and end (``eval_interval`` out of reach) and writes no checkpoint
    on the way; evaluations are timed on their own and added back in the extrapolation at the preset's
    interval. The window starts when the first collector batch is stored, so it leaves out start-up (the
    first batch, the first update, allocation of the replay) and it contains whole iterations: the updates
    after a batch, logging, and the next collection.
    """
    from mcrs.experiment.training.trainer import Experiment

    cfg = compose_config(
        map_name, quick, ["logger=csv", "logger.progress_bar=false", f"threads={threads}", *extra], algo
    )
    t = cfg.train
    eval_interval = int(t.eval_interval)
    batch_steps = int(t.num_envs) * int(cfg.env.max_steps)
    total = max(loop_steps, 4 * batch_steps)  # the window spans all batches but the first and last: >= 2
    t.total_env_steps, t.eval_interval, t.checkpoint_interval, t.save_replay = total, NEVER, NEVER, False
    marks: list[tuple[float, int, int, float]] = []  # (time, env steps, updates, update seconds so far)
    spent = [0.0]
    evals: list[float] = []
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="mcrs-bench-learner-") as run_dir:
        trainer = Experiment(cfg, run_dir)
        c = trainer.counters
        extend, update, evaluate = trainer.replay.extend, trainer._update, trainer.evaluate

        def marked_extend(*args: Any, **kwargs: Any) -> Any:
            marks.append((time.perf_counter(), c.env_steps, c.updates, spent[0]))
            return extend(*args, **kwargs)

        def timed_update() -> dict[str, torch.Tensor]:
            begin = time.perf_counter()
            try:
                return update()
            finally:
                spent[0] += time.perf_counter() - begin

        def timed_evaluate() -> dict[str, float]:
            begin = time.perf_counter()
            try:
                return evaluate()
            finally:
                evals.append(time.perf_counter() - begin)

        trainer.replay.extend = marked_extend  # instance attributes: the loop calls them through self
        trainer._update = timed_update
        trainer.evaluate = timed_evaluate
        trainer.run()
        total_steps = c.env_steps
    wall = time.perf_counter() - start
    (t0, s0, u0, x0), (t1, s1, u1, x1) = marks[1], marks[-1]
    return LoopResult(
        map_name=map_name,
        env_steps=s1 - s0,
        seconds=t1 - t0,
        updates=u1 - u0,
        update_seconds=x1 - x0,
        eval_seconds=evals[-1],
        eval_episodes=int(t.eval_episodes),
        eval_interval=eval_interval,
        total_steps=total_steps,
        wall_seconds=wall,
    )


_LAUNCHER_WORKER = (
    "import json, sys, torch\n"
    "from mcrs_benchmarks.loop import measure_loop\n"
    "map_name, steps, threads, quick = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4] == '1'\n"
    "torch.set_num_threads(threads)\n"
    "r = measure_loop(map_name, quick, steps, threads)\n"
    "print('RESULT ' + json.dumps({'steps': r.env_steps, 'seconds': r.seconds}))\n"
)


def launcher_rates(map_name: str, quick: bool, loop_steps: int) -> tuple[float, list[float]]:
    """Env-steps/s of one run with 2 torch threads alone, then of two 1-thread runs side by side (each in
    its own process, as the ``local2`` launcher starts them): how a sweep should share the 2 cores."""
    import json
    import subprocess

    def start(threads: int) -> subprocess.Popen:
        args = [
            sys.executable,
            "-c",
            _LAUNCHER_WORKER,
            map_name,
            str(loop_steps),
            str(threads),
            str(int(quick)),
        ]
        return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)

    def rate(proc: subprocess.Popen) -> float:
        out, _ = proc.communicate()
        if proc.returncode != 0:
            raise RuntimeError(f"a launcher benchmark run failed (exit {proc.returncode})")
        line = next(x for x in out.splitlines() if x.startswith("RESULT "))
        result = json.loads(line[len("RESULT ") :])
        return result["steps"] / result["seconds"]

    one = rate(start(2))
    pair = [start(1), start(1)]
    return one, [rate(p) for p in pair]


def collector_step_seconds(env_config: EnvConfig, num_envs: int, batches: int) -> float:
    """Seconds per collector step (env step, recurrent policy, exploration, TorchRL bookkeeping) for
    ``num_envs`` environments at once: why the presets collect many episodes per batch."""
    from torchrl.collectors import Collector
    from torchrl.envs import TransformedEnv

    from mcrs.env.torchrl_env import MCRSEnv
    from mcrs.models.acting import make_acting_policy, recurrent_primer
    from mcrs.models.agent import RecurrentAgent

    cfg = env_config.replace(num_envs=num_envs)
    env = TransformedEnv(MCRSEnv(cfg), recurrent_primer(num_envs, cfg.n_uavs, 64))
    agent = RecurrentAgent(cfg.obs_dim, N_ACTIONS, cfg.n_uavs)
    _, exploring, _ = make_acting_policy(agent, N_ACTIONS)
    collector = Collector(
        env, exploring, frames_per_batch=num_envs * cfg.max_steps, total_frames=-1, trust_policy=True,
        auto_register_policy_transforms=False,
    )  # fmt: skip
    try:
        batches_iter = iter(collector)
        next(batches_iter)  # warm-up
        start = time.perf_counter()
        for _ in range(batches):
            next(batches_iter)
        return (time.perf_counter() - start) / (batches * cfg.max_steps)
    finally:
        collector.shutdown()
