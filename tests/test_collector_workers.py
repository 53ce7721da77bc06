"""Multi-process collection (``train.collector=multiprocess``): same batch layout, synced weights, errors surfaced.

Each test starts worker processes (spawned: a few seconds each on a small machine), so the sizes are tiny.
"""

from __future__ import annotations

import copy
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.training.trainer import Experiment
from mcrs.train import resume_config
from tests.train_helpers import TINY, compose_config

pytestmark = pytest.mark.slow

MULTI = ("train.collector=multiprocess", "train.collector_workers=2")
T, ENVS = 10, 4  # TINY: 4 environments, 10-step episodes


def test_batch_is_whole_episodes_in_the_single_process_layout(tmp_path: Path) -> None:
    trainer = Experiment(compose_config(*MULTI, "train.total_env_steps=80"), tmp_path)
    single = Experiment(compose_config("train.total_env_steps=80"), tmp_path / "single")
    try:
        iterator = iter(trainer.collector)
        trainer.collector.start_batch(123)
        batch = trainer.collector.next_batch(iterator)
        single_iterator = iter(single.collector)
        single.collector.start_batch(123)
        reference = single.collector.next_batch(single_iterator)
    finally:
        trainer.collector.shutdown()
        single.collector.shutdown()
    assert batch.batch_size == reference.batch_size == torch.Size([ENVS, T])
    assert set(batch.keys(True, True)) == set(reference.keys(True, True))
    done = batch.get(("next", "done")).reshape(ENVS, T)
    assert done[:, -1].all() and not done[:, :-1].any()  # one whole episode per row
    steps = batch.get(("next", "metrics", "coverage")).reshape(ENVS, T)
    assert (steps[:, 0] > 0).all()  # every row starts a fresh episode (coverage grows from the start cells)
    # The two workers' environments were seeded differently: not the same episode twice.
    assert not torch.equal(batch[:2].get(("agents", "observation")), batch[2:].get(("agents", "observation")))


def test_training_with_workers_reaches_the_end_and_is_reproducible(tmp_path: Path) -> None:
    straight = Experiment(compose_config(*MULTI, "train.total_env_steps=160"), tmp_path / "straight")
    straight.run()
    assert straight.counters.env_steps == 160 and straight.counters.episodes == 16
    assert straight.counters.updates > 0
    half = Experiment(compose_config(*MULTI, "train.total_env_steps=80"), tmp_path / "half")
    half.run()
    overrides = [f"resume={tmp_path / 'half'}", "train.total_env_steps=160"]
    cfg, run_dir = resume_config(compose_config(*overrides), overrides)
    resumed = Experiment(cfg, run_dir, resume=True)
    resumed.run()
    for name, value in straight.learner.agent.state_dict().items():
        assert torch.equal(value, resumed.learner.agent.state_dict()[name]), name
    assert straight.counters == resumed.counters


def test_workers_act_with_the_learners_current_weights_and_epsilon(tmp_path: Path) -> None:
    """After training (large lr, so the weights move), a worker's greedy actions are the learner's."""
    cfg = compose_config(*MULTI, "train.total_env_steps=80", "train.lr=0.05", "train.eps_start=0",
                         "train.eps_end=0")  # fmt: skip
    trainer = Experiment(cfg, tmp_path)
    initial = copy.deepcopy(trainer.greedy)
    trainer.run()  # shuts its collector down: build a fresh one over the trained policy
    from mcrs.experiment.training.collection import TrainingCollector

    collector = TrainingCollector(
        "multiprocess", trainer.env, trainer.exploring, trainer.env_config, 16, 2, trainer.device
    )
    try:
        iterator = iter(collector)
        with torch.no_grad():  # move the weights after the workers started: they must follow
            trainer.learner.agent.fc1.weight.mul_(-1.0)
        collector.sync_weights()
        collector.start_batch(7)
        greedy_batch = collector.next_batch(iterator)
        trainer.epsilon.eps.fill_(1.0)  # then explore: every action random
        collector.sync_weights()
        collector.start_batch(7)
        random_batch = collector.next_batch(iterator)
    finally:
        collector.shutdown()
    assert _mismatches(trainer.greedy, greedy_batch) == 0
    assert _mismatches(initial, greedy_batch) > 0  # the check can tell stale weights from current ones
    assert _mismatches(trainer.greedy, random_batch) > 0  # epsilon reached the workers


def _mismatches(policy: torch.nn.Module, batch) -> int:
    """Actions of ``batch`` that ``policy`` would not have taken greedily, step by step."""
    action_key = ("agents", "action")
    count = 0
    for t in range(batch.shape[1]):
        step = batch[:, t].exclude(action_key, "next")
        with torch.no_grad():
            count += int((policy(step.clone()).get(action_key) != batch[:, t].get(action_key)).sum())
    return count


FAILING_RUN = textwrap.dedent(
    """
    from mcrs.env.torchrl_env import MCRSEnv

    _step, _calls = MCRSEnv._step, [0]


    def _failing_step(self, tensordict):
        _calls[0] += 1
        if _calls[0] > {fail_after}:
            raise RuntimeError("injected step failure in worker")
        return _step(self, tensordict)


    if __name__ == "__mp_main__":  # only inside the collector's (spawned) workers
        MCRSEnv._step = _failing_step

    if __name__ == "__main__":
        from mcrs.train import main

        main()
    """
)


def test_a_failing_worker_stops_the_run_with_its_cause_and_the_run_resumes(tmp_path: Path) -> None:
    script = tmp_path / "failing_run.py"
    script.write_text(FAILING_RUN.format(fail_after=3 * T))  # each worker fails in its 4th batch
    run_dir = tmp_path / "run"
    overrides = [
        "algo=qmix", *TINY, *MULTI, "train.total_env_steps=400", "train.checkpoint_interval=40",
        f"hydra.run.dir={run_dir}",
    ]  # fmt: skip
    env = {**os.environ, "HYDRA_FULL_ERROR": "1", "PYTHONPATH": str(Path.cwd())}
    done = subprocess.run(
        [sys.executable, str(script), *overrides], cwd=tmp_path, env=env, capture_output=True, text=True,
        timeout=300,
    )  # fmt: skip
    assert done.returncode != 0
    assert "mcrs-train: error: a collector worker failed: RuntimeError: injected step failure in worker" in (
        done.stderr
    ), done.stderr[-3000:]
    state = ckpt.load(ckpt.checkpoint_path(run_dir))
    assert state["counters"]["env_steps"] == 3 * ENVS * T  # the batches before the failure were saved

    resumed = subprocess.run(
        [sys.executable, "-m", "mcrs.train", f"resume={run_dir}"], cwd=tmp_path, env=env, capture_output=True,
        text=True, timeout=300,
    )  # fmt: skip
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert ckpt.load(ckpt.checkpoint_path(run_dir))["counters"]["env_steps"] == 400


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (("train.collector=multiprocess", "train.collector_workers=3"), "not divisible by"),
        (("train.collector_workers=0",), "must be >= 1"),
    ],
)
def test_bad_collector_settings_are_refused(overrides: tuple[str, ...], message: str) -> None:
    from mcrs.experiment.config import ConfigError, validate

    with pytest.raises(ConfigError, match=message):
        validate(compose_config(*overrides))


def _collector_workers(pid: int) -> list[int]:
    """The spawned collector workers among the children of process ``pid`` (not the resource tracker)."""
    children = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
    return [int(c) for c in children if b"spawn_main" in Path(f"/proc/{c}/cmdline").read_bytes()]


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="finds the workers through /proc (Linux)")
def test_a_killed_worker_ends_the_run_in_one_line_and_the_run_resumes(tmp_path: Path) -> None:
    """SIGKILL leaves no traceback in the worker, and TorchRL waits for its weight-update acknowledgement
    without a timeout: the run must neither hang nor end in a traceback (issue 33)."""
    import signal
    import time

    from tests.train_helpers import start_train

    run_dir = tmp_path / "run"
    overrides = [
        "algo=qmix", *TINY, *MULTI, "train.total_env_steps=100000", "train.checkpoint_interval=40",
        "train.eval_interval=100000", f"hydra.run.dir={run_dir}",
    ]  # fmt: skip
    proc = start_train(*overrides, cwd=tmp_path)
    try:
        deadline = time.monotonic() + 240
        while not ckpt.checkpoint_path(run_dir).is_file():  # the workers run: a checkpoint is written
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.2)
        workers = _collector_workers(proc.pid)
        assert len(workers) == 2, workers
        os.kill(workers[1], signal.SIGKILL)
        _, err = proc.communicate(timeout=120)  # no hang
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 1, err[-3000:]
    assert "Traceback" not in err, err[-3000:]
    errors = [line for line in err.splitlines() if line.startswith("mcrs-train: error:")]
    assert errors == [
        f"mcrs-train: error: a collector worker (pid {workers[1]}) died (signal 9, SIGKILL); the last "
        f"checkpoint {ckpt.checkpoint_path(run_dir)} is intact: resume={run_dir}"
    ], err[-3000:]
    steps = ckpt.load(ckpt.checkpoint_path(run_dir))["counters"]["env_steps"]
    assert steps > 0 and steps % (ENVS * T) == 0
    env = {**os.environ, "HYDRA_FULL_ERROR": "1"}
    resumed = subprocess.run(
        [sys.executable, "-m", "mcrs.train", f"resume={run_dir}", f"train.total_env_steps={steps + ENVS * T}"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert ckpt.load(ckpt.checkpoint_path(run_dir))["counters"]["env_steps"] == steps + ENVS * T


def test_a_wait_on_a_worker_that_dies_ends_instead_of_hanging() -> None:
    """The wait TorchRL makes for a weight update's acknowledgement has no timeout: a queue nobody writes
    to stands for it. The watch ends it when the worker dies."""
    import multiprocessing
    import signal
    import threading
    import time

    from mcrs.experiment.training.collection import CollectorWorkerFailed, WorkerWatch

    ctx = multiprocessing.get_context("spawn")
    worker = ctx.Process(target=time.sleep, args=(120,), daemon=True)
    worker.start()
    replies = ctx.Queue()
    watch = WorkerWatch([worker], interval=0.1)
    killer = threading.Timer(1.0, os.kill, (worker.pid, signal.SIGKILL))
    killer.start()
    started = time.monotonic()
    try:
        died = rf"^a collector worker \(pid {worker.pid}\) died \(signal 9, SIGKILL\)$"
        with pytest.raises(CollectorWorkerFailed, match=died), watch.waiting():
            replies.get()  # blocks for ever without the watch
        assert time.monotonic() - started < 30
        with pytest.raises(CollectorWorkerFailed), watch.waiting():  # every later wait fails at once
            pass
    finally:
        killer.cancel()
        watch.close()
        worker.kill()
        worker.join()
    assert signal.getsignal(signal.SIGUSR1) is signal.SIG_DFL  # the handler is put back
