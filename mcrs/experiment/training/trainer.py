"""An experiment: a value-factorisation learner trained on a task, MCRS-LCR by default, top to bottom::

    collector (masked epsilon-greedy) -> whole episodes -> replay buffer -> ValueFactorisationLoss -> optimiser
    callbacks add what an algorithm needs: the episodic memory, EMC's curiosity
    every eval_interval env steps: greedy evaluation on fixed-seed environments
    every checkpoint_interval env steps, every checkpoint_minutes and at the end: an atomic checkpoint
    on Ctrl-C or SIGTERM: the batch in progress ends, a checkpoint, RunInterrupted

    Experiment(compose("algo=qmix", "env=map20"), "outputs/my_run").run()
    Experiment(compose("algo=qplex"), "outputs/game", task=MatrixGameTask()).run()

The networks are initialised from ``seed``, collector batch ``k`` resets its environments from ``seed`` and
``k``, and exploration and replay sampling draw from torch's generator, whose state is in every checkpoint. A
resumed run thus repeats the straight run exactly on the CPU.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig

from mcrs.experiment.config import Config, as_typed, to_container, validate
from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.run.counters import Counters, batch_seed
from mcrs.experiment.run.interrupt import RunInterrupted, StopSignals
from mcrs.experiment.run.logging import (
    close_log_files,
    log_event,
    log_scalars,
    make_logger,
    metrics_line,
    progress_bar,
    quiet_torchrl,
)
from mcrs.experiment.run.replay_store import ReplayStore
from mcrs.experiment.run.run_state import RunState
from mcrs.experiment.run.rundir import RunDirError, RunLock, describe_os_error, prepare_fresh
from mcrs.experiment.training.algorithms import (
    ALGORITHMS,
    Algorithm,
    UnregisteredAlgorithm,
    algorithm_class,
    unregistered,
)
from mcrs.experiment.training.callbacks import (
    Callback,
    UnreadBatchKey,
    append_scalar,
    check_names,
    hook_scalars,
    unread_batch_keys,
)
from mcrs.experiment.training.collection import CollectorWorkerFailed, TrainingCollector
from mcrs.experiment.training.evaluation import EvaluationVideo, evaluate, make_eval_env
from mcrs.experiment.training.replay import episodes_from_rollout, make_episode_buffer
from mcrs.experiment.training.resources import check_buildable
from mcrs.experiment.training.task import (
    MCRSTask,
    Task,
    check_env,
    check_supported,
    make_task,
    with_agent_state,
)
from mcrs.experiment.training.whole_batches import rounding_notes
from mcrs.experiment.util.threads import SpeedCheck, apply_threads
from mcrs.models.acting import make_acting_policy
from mcrs.objectives.gradient import TrainingDiverged

__all__ = ["Counters", "Experiment", "TrainingDiverged", "batch_seed"]


class Experiment:
    """A training run built from a config (or the Hydra ``DictConfig`` it is composed into): :meth:`run`
    trains it, :meth:`evaluate` evaluates the greedy policy, and :attr:`state` keeps the bookkeeping and
    checkpoints. ``callbacks`` run after the algorithm's own; ``task`` defaults to ``config.task``'s, else
    MCRS on ``config.env``."""

    def __init__(
        self,
        config: Config | DictConfig,
        run_dir: str | Path,
        resume: bool = False,
        callbacks: list[Callback] | None = None,
        task: Task | None = None,
    ) -> None:
        check_names(list(callbacks or []))  # before anything is built or written
        self.config = as_typed(config)
        self.env_config = validate(self.config)  # the one validation of the run; the env is built from it
        check_buildable(self.config, self.env_config)  # the embedding fits the map, the run the machine
        if task is None and self.config.task is not None:  # task=... on the command line, or a resume
            task = make_task(self.config.task)
        self.task = MCRSTask(self.env_config) if task is None else task
        self._raw_env = None
        if not isinstance(self.task, MCRSTask):  # recorded: the tools rebuild the task from config.yaml
            self.config = replace(self.config, task=self.task.spec())
            # the contract, checked before anything is written or locked: a refusal leaves nothing behind
            self._raw_env = self.task.make_env(
                self.config.train.num_envs, torch.device(self.env_config.device)
            )
            check_env(self.task, self._raw_env)
        check_supported(self.config, self.task)  # ConfigError: what the task cannot run (logger.video, ...)
        # the algorithm's class now, its instance in _build after torch's seed; its options get their defaults
        self.algorithm_class: type[Algorithm] = algorithm_class(self.config.algo)
        self.config = replace(self.config, algo=self.algorithm_class.with_options(self.config.algo))
        self.run_dir = Path(run_dir)
        # One writer per run directory: a second run there, or a resume of a live run, stops here.
        self._lock: RunLock | None = RunLock(self.run_dir)
        try:
            self._build(resume, list(callbacks or []))
        except BaseException:
            self.close()
            raise

    @property
    def seconds(self) -> dict[str, float]:
        """This session's wall seconds by part (``collect``, ``update``, ``eval`` and each callback)."""
        return dict(self._timer)

    # ------------------------------------------------------------------ the run's state (RunState)
    @property
    def counters(self) -> Counters:
        """The run's progress: env steps, episodes, updates and when the next events are due."""
        return self.state.counters

    @property
    def last_eval(self) -> dict[str, float]:
        """The latest greedy evaluation's means (empty before the first)."""
        return self.state.last_eval

    @property
    def replay_store(self) -> ReplayStore:
        """The replay's block files beside ``last.pt``."""
        return self.state.replay_store

    def state_dict(self, replay_inline: bool = True) -> dict[str, Any]:
        """Everything a checkpoint holds."""
        return self.state.state_dict(replay_inline)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a checkpoint's state."""
        self.state.load_state_dict(state)

    def fingerprint(
        self, config: dict[str, Any] | None = None, learner: dict[str, Any] | None = None
    ) -> dict:
        """What a checkpoint must share with this run."""
        return self.state.fingerprint(config, learner)

    def save(self, name: str = ckpt.LAST) -> Path:
        """Write a checkpoint (``checkpoints/last.pt``, or ``name``) and the weights at this step."""
        return self.state.save(name)

    def close(self) -> None:
        """Close the log files and release the run directory; :meth:`run` and the process's exit do it too."""
        if getattr(self, "logger", None) is not None:
            close_log_files(self.logger)
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    def _build(self, resume: bool, extra_callbacks: list[Callback]) -> None:
        cfg, t = self.config, self.config.train
        quiet_torchrl()  # before the replay is built or loaded: TorchRL prints an INFO line for it
        if not resume:  # a fresh run never mixes its files with another run's
            prepare_fresh(self.run_dir, cfg.overwrite)
        self.threads = apply_threads(cfg.threads)  # auto: the cores the load leaves free
        self.device = torch.device(self.env_config.device)
        torch.manual_seed(int(cfg.seed))
        self.T = self.task.max_steps
        self.algorithm = self.algorithm_class(cfg.algo)  # its parts: mixer, loss, learner, callbacks
        self.learner = self.algorithm.learner(cfg.model, t, self.task, self.device)
        self.callbacks = self.algorithm.callbacks(cfg, self.env_config, self.learner, self.device)
        self.callbacks += extra_callbacks
        check_names(self.callbacks)
        self.greedy, self.exploring, self.epsilon = make_acting_policy(
            self.learner.agent,
            self.task.n_actions,
            eps_start=t.eps_start,
            eps_end=t.eps_end,
            eps_anneal_steps=t.eps_anneal_steps,
            group=self.task.group,
        )
        hidden, task = cfg.model.hidden_dim, self.task
        raw_env = self._raw_env if self._raw_env is not None else task.make_env(t.num_envs, self.device)
        self._raw_env = None
        check_env(task, raw_env)  # the networks above were built from the task's declared sizes
        self.env = with_agent_state(raw_env, task, t.num_envs, hidden, self.device)
        self.eval_env = make_eval_env(task, t.eval_episodes, hidden, self.device)
        self.video = EvaluationVideo(self.env_config, hidden, self.device, int(t.eval_seed))  # MCRS only
        self.replay = make_episode_buffer(t.replay_episodes, t.batch_episodes, device=self.device)
        self.state = RunState(
            self, Counters(next_checkpoint=t.checkpoint_interval, next_target_update=t.target_update_episodes)
        )
        self._batch_keys_checked = False  # the callbacks' batch keys are checked on the first update
        self._timer = {"collect": 0.0, "update": 0.0, "eval": 0.0, **{cb.name: 0.0 for cb in self.callbacks}}
        for callback in self.callbacks:
            callback.on_setup(self)
        if resume:
            self.state.load(ckpt.checkpoint_path(self.run_dir))
        else:
            self.state.write_config()
        lg = cfg.logger
        self.logger = make_logger(
            str(lg.backend), self.run_dir, to_container(cfg), lg.project, str(lg.wandb_mode)
        )
        self.collector = TrainingCollector(  # whole episodes: every batch row is one episode
            str(t.collector),
            self.env,
            self.exploring,
            task,
            hidden,
            t.collector_workers,
            self.device,
            t.num_envs,
        )
        if resume:  # last: building the collector may draw random numbers
            self.state.restore_rng()
        log_event(f"{'resuming' if resume else 'training'} {cfg.algo.name} on {self.task.name}")
        if self.algorithm_note:  # a label of one's own, or a misspelt name: said, not refused
            log_event(self.algorithm_note)
            warnings.warn(UnregisteredAlgorithm(self.algorithm_note), stacklevel=3)
        for note in rounding_notes(t.num_envs * self.T, t.total_env_steps, t.eval_interval):
            log_event(note)
        if t.updates_per_episode == 0:  # allowed (a collection-only run), never silent
            log_event(
                "train.updates_per_episode=0: the run collects and evaluates but never updates the networks"
            )

    @property
    def algorithm_note(self) -> str | None:
        """What an unregistered ``algo.name`` trains, said in the log and by ``mcrs-train``; None for a
        registered one."""
        name = str(self.config.algo.name)
        if name in ALGORITHMS:
            return None
        return unregistered(name, f"trained as the built-in {self.algorithm!r}")

    def callback(self, name: str) -> Callback:
        """The callback called ``name``."""
        for callback in self.callbacks:
            if callback.name == name:
                return callback
        raise KeyError(f"no callback {name!r}; this experiment has {[c.name for c in self.callbacks]}")

    # ------------------------------------------------------------------ the loop
    @property
    def finished(self) -> bool:
        """Whether the run is at ``train.total_env_steps`` with its final evaluation written."""
        return (
            self.counters.env_steps >= self.config.train.total_env_steps
            and self.state.final_evaluation_written()
        )

    def run(self) -> dict[str, float]:
        """Train until ``train.total_env_steps``; returns the last evaluation's metrics."""
        t, counts = self.config.train, self.counters
        self._session_start_steps = counts.env_steps
        if self.finished:  # a resumed run that had finished
            log_event(
                f"the run is finished at env step {counts.env_steps}: nothing to train, evaluate or save"
            )
            self.state.evaluated_at = counts.env_steps  # its final evaluation is logged at this step
            self.collector.shutdown()
            self.close()
            return dict(self.last_eval)  # its final evaluation is logged once, by the session that ended it
        progress = progress_bar(
            self.config.train.total_env_steps,
            counts.env_steps,
            self.config.logger.progress_bar,
            f"{self.config.algo.name} {self.task.name}",
        )
        self._timer = dict.fromkeys(self._timer, 0.0)  # this session's clock
        collector_iter = iter(self.collector)
        self.state.last_save = time.monotonic()
        self._speed = SpeedCheck(self.threads, str(t.collector) == "single")
        stats: dict[str, list[torch.Tensor]] = {}
        with StopSignals() as stop:  # a signal: a checkpoint after this batch; more signals are ignored
            try:
                while counts.env_steps < t.total_env_steps:
                    if counts.env_steps >= counts.next_eval:
                        self.evaluate()
                        counts.next_eval += t.eval_interval
                    batch = self._collect(collector_iter, stats)  # num_envs whole episodes, into the replay
                    self._learn(stats)  # updates_per_episode updates per collected episode
                    if counts.env_steps >= counts.next_log:
                        self._log_train(stats)
                        stats = {}
                        counts.next_log = counts.env_steps + self.config.logger.log_interval
                    saved = self._checkpoint_if_due()
                    progress.update(batch.numel())
                    progress.set_postfix(self._postfix(), refresh=False)
                    if stop.requested:  # a consistent point: the batch is in the replay, its updates done
                        path = saved or self.save()
                        raise RunInterrupted(int(stop.signum or 0), self.run_dir, counts.env_steps, path)
                    self._speed.observe()
                self.evaluate()
                progress.set_postfix(self._postfix())  # the bar's last line shows the final evaluation
                if counts.env_steps >= counts.next_eval:  # a resume from this checkpoint must not repeat it
                    counts.next_eval += t.eval_interval
                if stats:  # batches since the last row (none: that row is already at this step)
                    self._log_train(stats)
                self.save()
            except OSError as error:  # a full disk or a vanished directory: one line, not a trace
                raise RunDirError(
                    f"cannot continue the run: {describe_os_error(error)}{self.state.intact()}"
                ) from None
            except CollectorWorkerFailed as error:  # the batch is lost; the last checkpoint is a whole state
                raise CollectorWorkerFailed(f"{error}{self.state.intact('')}") from None
            finally:
                progress.close()
                self.collector.shutdown()
                self.close()
        return dict(self.last_eval)

    def _collect(self, collector_iter, stats: dict[str, list[torch.Tensor]]):
        """Collect num_envs whole episodes with the exploring policy into the replay, then hand them to the
        callbacks."""
        t, counts = self.config.train, self.counters
        start = time.perf_counter()
        self.epsilon.set_env_steps(counts.env_steps)
        self.collector.sync_weights()
        self.collector.start_batch(batch_seed(int(self.config.seed), counts.iteration))
        batch = self.collector.next_batch(collector_iter)
        self._check_finite(batch)
        task = self.task
        episodes = episodes_from_rollout(  # one item per row: its first episode, padded to T + 1
            batch,
            task.step_keys,
            task.action_key,
            time_limit=str(self.config.algo.time_limit),
            first_episode_only=True,
        )
        episode_ids = counts.episodes + torch.arange(t.num_envs, device=episodes.device)
        episodes.set("episode", episode_ids.unsqueeze(1).expand(episodes.batch_size).clone())
        self.state.replay_store.mark_written(self.replay.extend(episodes))
        for name, values in task.episode_metrics(batch).items():
            append_scalar(stats, f"train/{name}", values.mean())
        counts.iteration += 1
        counts.episodes += t.num_envs
        counts.env_steps += batch.numel()
        self._timer["collect"] += time.perf_counter() - start
        for callback in self.callbacks:
            start = time.perf_counter()
            returned = callback.on_batch_collected(batch, episode_ids)
            for key, value in hook_scalars(callback, "on_batch_collected", returned).items():
                append_scalar(stats, key, value)
            self._timer[callback.name] += time.perf_counter() - start
        return batch

    def _learn(self, stats: dict[str, list[torch.Tensor]]) -> None:
        """The updates owed for the episodes collected so far, then the target networks' copy when due."""
        t, counts = self.config.train, self.counters
        start = time.perf_counter()
        if len(self.replay) >= t.batch_episodes:
            counts.update_credit += t.num_envs * t.updates_per_episode
            while counts.update_credit >= 1.0:
                for key, value in self._update().items():
                    append_scalar(stats, key, value)
                counts.update_credit -= 1.0
        if counts.episodes >= counts.next_target_update:  # once per target_update_episodes episodes
            self.learner.target_updater.step()
            counts.next_target_update += t.target_update_episodes * (
                1 + (counts.episodes - counts.next_target_update) // t.target_update_episodes
            )
        self._timer["update"] += time.perf_counter() - start

    def _update(self) -> dict[str, torch.Tensor]:
        """One learner update on a sampled batch, after the callbacks have added their keys to it."""
        counts = self.counters
        try:
            batch = self.replay.sample()
            out: dict[str, torch.Tensor] = {}
            for callback in self.callbacks:
                start = time.perf_counter()
                before = None if self._batch_keys_checked else set(batch.keys(True, True))
                returned = callback.on_train_batch(batch, counts.env_steps)
                out.update(hook_scalars(callback, "on_train_batch", returned))
                if before is not None:  # the session's first update: a key the loss never reads is said
                    note = unread_batch_keys(
                        callback, set(batch.keys(True, True)) - before, self.learner.loss
                    )
                    if note:
                        log_event(note)
                        warnings.warn(UnreadBatchKey(note), stacklevel=2)
                spent = time.perf_counter() - start
                self._timer[callback.name] += spent
                self._timer["update"] -= spent  # _learn's clock runs around this: count it once
            self._batch_keys_checked = True
            stats = self.learner.update(batch, counts.env_steps)
        except TrainingDiverged as error:
            path = self.save(name="last_good.pt")
            raise TrainingDiverged(
                f"{error} (update {counts.updates + 1}); the last good state is saved in {path}"
            ) from None
        counts.updates += 1
        return {**{f"train/{k}": v for k, v in stats.items()}, **out}

    def _checkpoint_if_due(self) -> Path | None:
        t, counts = self.config.train, self.counters
        due_by_steps = counts.env_steps >= counts.next_checkpoint and counts.env_steps > 0
        due_by_time = (
            t.checkpoint_minutes > 0 and time.monotonic() - self.state.last_save >= 60 * t.checkpoint_minutes
        )
        if due_by_steps:
            counts.next_checkpoint += t.checkpoint_interval  # first: a resume must not save again
        return self.save() if due_by_steps or due_by_time else None

    def _check_finite(self, batch) -> None:
        """Stop before a NaN or inf from the env reaches the replay or the memory."""
        finite_keys = ((self.task.state_key, "belief maps / state"), (("next", "reward"), "reward"),
                       (self.task.observation_key, "observation"))  # fmt: skip
        for key, term in finite_keys:
            if not bool(torch.isfinite(batch.get(key)).all()):
                path = self.save(name="last_good.pt")
                raise TrainingDiverged(
                    f"non-finite {term} in the episodes collected after env step {self.counters.env_steps}; "
                    f"the last good state is saved in {path}"
                )

    # ------------------------------------------------------------------ evaluation and logging
    def evaluate(self) -> dict[str, float]:
        """Greedy evaluation on ``train.eval_episodes`` fixed-seed episodes, logged at the current step. At a
        step already logged it logs nothing and skips ``on_evaluation_end``, which would move EMU-change's
        threshold twice."""
        start = time.perf_counter()
        self.state.last_eval = evaluate(
            self.eval_env, self.greedy, int(self.config.train.eval_seed), self.task
        )
        self.state.last_eval_step = self.counters.env_steps
        if self.state.evaluated_at == self.counters.env_steps:
            self._timer["eval"] += time.perf_counter() - start
            return dict(self.last_eval)
        if self.config.logger.video:  # one more greedy episode, drawn frame by frame: eval/video
            self.video.log(self.logger, self.run_dir, self.greedy, self.counters.env_steps)
        self._timer["eval"] += time.perf_counter() - start
        self._log({f"eval/{k}": v for k, v in self.last_eval.items()}, self.counters.env_steps)
        log_event(f"evaluation at env step {self.counters.env_steps}: {metrics_line(self.last_eval)}")
        for callback in self.callbacks:
            callback.on_evaluation_end(self.last_eval)
        self.state.evaluated_at = self.counters.env_steps
        return dict(self.last_eval)

    def _log_train(self, stats: dict[str, list[torch.Tensor]]) -> None:
        counts = self.counters
        values = {name: torch.stack(v).float().mean().item() for name, v in stats.items() if v}
        values["train/epsilon"] = float(self.epsilon.eps)
        values["train/episodes"] = counts.episodes
        values["train/updates"] = counts.updates
        values["train/replay_episodes"] = len(self.replay)
        for callback in self.callbacks:
            returned = hook_scalars(callback, "statistics", callback.statistics())
            values.update({k: float(v) for k, v in returned.items()})
        elapsed = sum(self._timer.values())
        values.update({f"time/{k}_s": v for k, v in self._timer.items()})
        if elapsed > 0:  # steps of this session (a resumed run starts its clock again)
            values["time/env_steps_per_s"] = (counts.env_steps - self._session_start_steps) / elapsed
        self._log(values, counts.env_steps)

    def _log(self, values: dict[str, float], step: int) -> None:
        """Log and count the rows of each metric, so that a resume can drop rows logged after its checkpoint."""
        log_scalars(self.logger, values, step)
        for name in values:
            self.state.log_rows[name] = self.state.log_rows.get(name, 0) + 1

    def _postfix(self) -> dict[str, str]:
        post = {"eps": f"{float(self.epsilon.eps):.3f}"}
        if self.last_eval:
            post["eval_reward"] = f"{self.last_eval['episode_reward']:.1f}"
        return post
