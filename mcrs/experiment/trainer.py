"""Training a value-factorisation learner on MCRS-LCR, top to bottom.

    collector (TorchRL, masked epsilon-greedy)  ->  whole episodes  ->  replay buffer (TorchRL)
        ->  ValueFactorisationLoss (TorchRL LossModule, TorchRL mixers)  ->  optimiser, HardUpdate
    with an episodic memory (algo.memory.enabled): the episodes also go into D_E (Algorithm 1), phi is
        retrained every t_emb env steps, and the replay's EpisodicLookup transform attaches H(phi(s'))
        to every sampled batch (mcrs.experiment.episodic); EMC's curiosity runs inside Learner.update
    every eval_interval env steps: greedy evaluation on fixed-seed environments
    every checkpoint_interval env steps, every checkpoint_minutes of wall clock and at the end: an atomic
        checkpoint of everything; the replay goes into block files beside it, and a checkpoint rewrites
        only the blocks with episodes added since the previous one (mcrs.experiment.replay_store)

Determinism: the networks are initialised from ``seed``; collector batch ``k`` resets its environments
from ``seed`` and ``k``; exploration and replay sampling draw from torch's generator, whose state is in
every checkpoint. So a run resumed from a checkpoint repeats the straight run exactly on the CPU.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from torch import nn
from torchrl.envs import TransformedEnv
from torchrl.objectives import HardUpdate

from mcrs.env.config import EnvConfig, from_mapping
from mcrs.env.core import METRICS, N_ACTIONS
from mcrs.env.torchrl_env import MCRSEnv
from mcrs.experiment import checkpoint as ckpt
from mcrs.experiment.collection import TrainingCollector
from mcrs.experiment.config import to_container, validate
from mcrs.experiment.episodic import EpisodicSide
from mcrs.experiment.evaluation import evaluate, make_eval_env
from mcrs.experiment.logging import log_scalars, make_logger
from mcrs.experiment.replay import (
    episodes_from_rollout,
    load_replay_state_dict,
    make_episode_buffer,
    replay_state_dict,
)
from mcrs.experiment.replay_store import ReplayStore
from mcrs.experiment.rundir import (
    RunDirError,
    RunLock,
    describe_os_error,
    fingerprint,
    first_difference,
    io_errors,
    prepare_fresh,
    truncate_csv_logs,
)
from mcrs.models.acting import make_acting_policy, recurrent_primer
from mcrs.models.agent import RecurrentAgent
from mcrs.models.mixers import make_mixer
from mcrs.objectives import ValueFactorisationLoss
from mcrs.objectives.curiosity import EMCCuriosity
from mcrs.objectives.gradient import TrainingDiverged, gradient_step


@dataclass
class Counters:
    """Progress of a run; saved in every checkpoint."""

    env_steps: int = 0
    episodes: int = 0
    updates: int = 0
    iteration: int = 0  # collector batches
    update_credit: float = 0.0  # fractional learner updates owed (updates_per_episode < 1)
    next_target_update: int = 0  # episode count at which the target networks are next copied
    next_eval: int = 0
    next_checkpoint: int = 0
    next_log: int = 0
    next_embedding: int = 0  # env step of the next training of the memory's embedding


def batch_seed(seed: int, iteration: int) -> int:
    """Seed of the environments of collector batch ``iteration`` (a run-local, reproducible stream)."""
    return (seed * 1_000_003 + iteration) % (2**63)


def build_agent(cfg: DictConfig, env_config: EnvConfig) -> RecurrentAgent:
    m = cfg.model
    return RecurrentAgent(
        env_config.obs_dim, N_ACTIONS, env_config.n_uavs, m.hidden_dim, m.agent_id, m.last_action
    )


def build_mixer(cfg: DictConfig, env_config: EnvConfig) -> nn.Module:
    a = cfg.algo
    return make_mixer(
        a.mixer,
        env_config.n_uavs,
        (env_config.state_dim,),
        N_ACTIONS,
        mixing_embed_dim=a.mixing_embed_dim,
        hypernet_embed=a.hypernet_embed,
        hypernet_layers=a.hypernet_layers,
        n_kernels=a.qplex_kernels,
        adv_hypernet_layers=a.qplex_adv_layers,
    )


def make_optimizer(params: list[nn.Parameter], t: DictConfig) -> torch.optim.Optimizer:
    """The ``train.optimizer`` of the config over ``params`` (the learner's and EMC's curiosity nets)."""
    if t.optimizer == "adam":
        return torch.optim.Adam(params, lr=t.lr, eps=t.optim_eps)
    return torch.optim.RMSprop(params, lr=t.lr, alpha=t.rmsprop_alpha, eps=t.optim_eps)


class Learner:
    """Networks, loss, optimiser and target updates: one :meth:`update` per sampled batch of episodes."""

    def __init__(self, cfg: DictConfig, env_config: EnvConfig, device: torch.device) -> None:
        t = cfg.train
        self.agent = build_agent(cfg, env_config).to(device)
        self.mixer = build_mixer(cfg, env_config).to(device)
        a = cfg.algo
        self.loss = ValueFactorisationLoss(
            self.agent,
            self.mixer,
            gamma=a.gamma,
            td_lambda=a.td_lambda,
            double_q=a.double_q,
            memory_weight=a.memory_weight,
            incentive=a.incentive,
        )
        self.params = [*self.agent.parameters(), *self.mixer.parameters()]
        self.curiosity = (
            EMCCuriosity(
                self.agent,
                gamma=a.gamma,
                scale=a.curiosity_scale,
                decay_rate=a.curiosity_decay_rate,
                decay_cycle=a.curiosity_decay_cycle,
                tau=a.curiosity_tau,
                grad_clip=t.grad_clip,
                make_optimizer=lambda params: make_optimizer(params, t),
            )
            if a.curiosity_scale > 0
            else None
        )
        self.optimizer = make_optimizer(self.params, t)
        # interval 0: every step() copies; the trainer calls it every target_update_episodes episodes.
        self.target_updater = HardUpdate(self.loss, value_network_update_interval=0)
        self.grad_clip = t.grad_clip

    def update(self, batch, step: int) -> dict[str, torch.Tensor]:
        """One gradient step; raises :class:`TrainingDiverged` before touching the weights on NaN/inf."""
        extra: dict[str, torch.Tensor] = {}
        if self.curiosity is not None:  # EMC: the intrinsic reward enters the TD target
            self.curiosity.set_env_steps(step)
            intrinsic, extra = self.curiosity.update(batch, step)
            batch.set("intrinsic_reward", intrinsic)
        out = self.loss(batch)
        term = "loss"
        if not torch.isfinite(out["loss"]):  # name the term that broke (the memory term is weighted inside)
            term = next((k for k in ("loss_td", "loss_memory") if not torch.isfinite(out[k])), term)
        grad_norm = gradient_step(out["loss"], self.optimizer, self.params, self.grad_clip, step, term)
        stats = {k: v.detach() for k, v in out.items() if k != "loss"}
        return {**stats, **extra, "grad_norm": grad_norm.detach()}

    def state_dict(self) -> dict[str, Any]:
        return {
            "agent": self.agent.state_dict(),
            "mixer": self.mixer.state_dict(),
            "target_agent": self.loss.target_agent_network_params.state_dict(),
            "target_mixer": self.loss.target_mixer_params.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            **({"curiosity": self.curiosity.state_dict_all()} if self.curiosity is not None else {}),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.agent.load_state_dict(state["agent"])
        self.mixer.load_state_dict(state["mixer"])
        self.loss.target_agent_network_params.load_state_dict(state["target_agent"])
        self.loss.target_mixer_params.load_state_dict(state["target_mixer"])
        self.optimizer.load_state_dict(state["optimizer"])
        if self.curiosity is not None:
            self.curiosity.load_state_dict_all(state["curiosity"])


class Trainer:
    """Everything a run needs, built from a validated config; :meth:`train` runs it.

    Args:
        cfg: the composed config (``conf/config.yaml``).
        run_dir: where logs and checkpoints go (a fresh run) or come from (``resume=True``).
        resume: continue from ``run_dir/checkpoints/last.pt``.
    """

    def __init__(self, cfg: DictConfig, run_dir: str | Path, resume: bool = False) -> None:
        validate(cfg)
        self.cfg, self.run_dir = cfg, Path(run_dir)
        # One writer per run directory: a second run there, or a resume of a live run, stops here.
        self._lock: RunLock | None = RunLock(self.run_dir)
        try:
            self._build(cfg, resume)
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        """Release the run directory (done by :meth:`train`; the process's exit does it too)."""
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    def _build(self, cfg: DictConfig, resume: bool) -> None:
        if not resume:  # a fresh run never mixes its files with another run's
            prepare_fresh(self.run_dir, bool(cfg.get("overwrite", False)))
        self._log_rows: dict[str, int] = {}  # rows written to each log (kept in checkpoints)
        self._saved_steps: int | None = None  # env steps of the last checkpoint this session wrote
        if cfg.threads:
            torch.set_num_threads(int(cfg.threads))
        self.device = torch.device(cfg.device)
        torch.manual_seed(int(cfg.seed))
        t = cfg.train
        self.env_config = from_mapping(cfg.env).replace(num_envs=t.num_envs, device=str(self.device))
        self.T = self.env_config.max_steps
        self.learner = Learner(cfg, self.env_config, self.device)
        self.greedy, self.exploring, self.epsilon = make_acting_policy(
            self.learner.agent,
            N_ACTIONS,
            eps_start=t.eps_start,
            eps_end=t.eps_end,
            eps_anneal_steps=t.eps_anneal_steps,
        )
        self.env = TransformedEnv(
            MCRSEnv(self.env_config),
            recurrent_primer(t.num_envs, self.env_config.n_uavs, cfg.model.hidden_dim, device=self.device),
        )
        self.eval_env = make_eval_env(self.env_config, t.eval_episodes, cfg.model.hidden_dim, self.device)
        self.replay = make_episode_buffer(t.replay_episodes, t.batch_episodes, device=self.device)
        self.replay_store = ReplayStore(ckpt.checkpoint_path(self.run_dir).parent)
        self.episodic = EpisodicSide(cfg, self.env_config, self.device) if cfg.algo.memory.enabled else None
        if self.episodic is not None:  # every sampled batch carries the memory's H(phi(s_{t+1}))
            self.replay.append_transform(self.episodic.lookup_transform())
        self.counters = Counters(
            next_checkpoint=t.checkpoint_interval,
            next_embedding=cfg.algo.memory.embedding_interval,
            next_target_update=t.target_update_episodes,
        )
        self.last_eval: dict[str, float] = {}
        if resume:
            self._load(ckpt.checkpoint_path(self.run_dir))
        else:
            with io_errors(f"write {self.run_dir / 'config.yaml'}"):
                self.run_dir.mkdir(parents=True, exist_ok=True)
                (self.run_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
        self.logger = make_logger(
            cfg.logger.backend, self.run_dir, to_container(cfg), cfg.logger.project, cfg.logger.wandb_mode
        )
        self.collector = TrainingCollector(  # whole episodes: every batch row is one episode
            t.collector,
            self.env,
            self.exploring,
            self.env_config,
            cfg.model.hidden_dim,
            t.collector_workers,
            self.device,
        )
        if resume:  # last: building the collector may draw random numbers
            rng = self._resume_rng
            del self._resume_rng
            torch.set_rng_state(rng["torch"].cpu())
            if "cuda" in rng and torch.cuda.is_available():
                torch.cuda.set_rng_state_all([s.cpu() for s in rng["cuda"]])

    # ------------------------------------------------------------------ the loop
    def train(self) -> dict[str, float]:
        """Run until ``train.total_env_steps``; returns the last evaluation's metrics."""
        t, c = self.cfg.train, self.counters
        self._session_start_steps = c.env_steps
        progress = self._progress_bar()
        train_stats: dict[str, list[torch.Tensor]] = {}
        timer = {"collect": 0.0, "memory": 0.0, "update": 0.0, "eval": 0.0}
        collector_iter = iter(self.collector)
        self._last_save = time.monotonic()
        try:
            while c.env_steps < t.total_env_steps:
                if c.env_steps >= c.next_eval:
                    self._evaluate(timer)
                    c.next_eval += t.eval_interval

                # Collect num_envs whole episodes with the exploring policy.
                start = time.perf_counter()
                self.epsilon.set_env_steps(c.env_steps)
                self.collector.sync_weights()
                self.collector.start_batch(batch_seed(int(self.cfg.seed), c.iteration))
                batch = self.collector.next_batch(collector_iter)
                self._check_finite(batch)
                episodes = episodes_from_rollout(batch)
                episode_ids = c.episodes + torch.arange(t.num_envs, device=episodes.device)
                episodes.set("episode", episode_ids.unsqueeze(1).expand(episodes.batch_size).clone())
                self.replay_store.mark_written(self.replay.extend(episodes))
                for name in METRICS:
                    train_stats.setdefault(f"train/{name}", []).append(
                        batch.get(("next", "metrics", name))[:, -1].mean()
                    )
                c.iteration += 1
                c.episodes += t.num_envs
                c.env_steps += batch.numel()
                timer["collect"] += time.perf_counter() - start

                if self.episodic is not None:  # Algorithm 1 on the new episodes; phi every t_emb steps
                    start = time.perf_counter()
                    last_reward = self.last_eval.get("episode_reward")
                    for key, value in self.episodic.insert(batch, episode_ids, last_reward).items():
                        train_stats.setdefault(key, []).append(torch.tensor(value))
                    if c.env_steps >= c.next_embedding:
                        for key, value in self.episodic.train_embedding().items():
                            train_stats.setdefault(key, []).append(torch.tensor(value))
                        c.next_embedding += self.cfg.algo.memory.embedding_interval
                    timer["memory"] += time.perf_counter() - start

                # Learn: updates_per_episode updates per collected episode, once a batch can be sampled.
                start = time.perf_counter()
                if len(self.replay) >= t.batch_episodes:
                    c.update_credit += t.num_envs * t.updates_per_episode
                    while c.update_credit >= 1.0:
                        stats = self._update()
                        for key, value in stats.items():
                            train_stats.setdefault(f"train/{key}", []).append(value)
                        c.update_credit -= 1.0
                if c.episodes >= c.next_target_update:  # once per target_update_episodes episodes
                    self.learner.target_updater.step()
                    c.next_target_update += t.target_update_episodes * (
                        1 + (c.episodes - c.next_target_update) // t.target_update_episodes
                    )
                timer["update"] += time.perf_counter() - start

                if c.env_steps >= c.next_log:
                    self._log_train(train_stats, timer)
                    train_stats = {}
                    c.next_log = c.env_steps + self.cfg.logger.log_interval
                due_by_steps = c.env_steps >= c.next_checkpoint and c.env_steps > 0
                due_by_time = (
                    t.checkpoint_minutes > 0
                    and time.monotonic() - self._last_save >= 60 * t.checkpoint_minutes
                )
                if due_by_steps:
                    c.next_checkpoint += t.checkpoint_interval  # first: a resume must not save again
                if due_by_steps or due_by_time:
                    self.save()
                progress.update(batch.numel())
                progress.set_postfix(self._postfix(), refresh=False)
            self._evaluate(timer)
            if c.env_steps >= c.next_eval:  # done: a resume from this checkpoint must not repeat it
                c.next_eval += t.eval_interval
            if train_stats:  # batches since the last row (none: that row is already at this step)
                self._log_train(train_stats, timer)
            self.save()
        except OSError as error:  # a full disk or a vanished directory while logging: one line, not a trace
            raise RunDirError(
                f"cannot continue the run: {describe_os_error(error)}{self._intact()}"
            ) from None
        finally:
            progress.close()
            self.collector.shutdown()
            self.close()
        return dict(self.last_eval)

    #: What a collected batch must hold finite, and how an error names it.
    FINITE_KEYS = (("state", "belief maps / state"), (("next", "reward"), "reward"),
                   (("agents", "observation"), "observation"))  # fmt: skip

    def _check_finite(self, batch) -> None:
        """Stop before a NaN or inf from the env (a belief, a reward) reaches the replay or the memory."""
        for key, term in self.FINITE_KEYS:
            if not bool(torch.isfinite(batch.get(key)).all()):
                path = self.save(name="last_good.pt")
                raise TrainingDiverged(
                    f"non-finite {term} in the episodes collected after env step {self.counters.env_steps}; "
                    f"the last good state is saved in {path}"
                )

    def _update(self) -> dict[str, torch.Tensor]:
        c = self.counters
        try:
            stats = self.learner.update(self.replay.sample(), c.env_steps)
        except TrainingDiverged as error:
            path = self.save(name="last_good.pt")
            raise TrainingDiverged(
                f"{error} (update {c.updates + 1}); the last good state is saved in {path}"
            ) from None
        c.updates += 1
        return stats

    # ------------------------------------------------------------------ evaluation and logging
    def _evaluate(self, timer: dict[str, float]) -> None:
        start = time.perf_counter()
        self.last_eval = evaluate(self.eval_env, self.greedy, int(self.cfg.train.eval_seed))
        timer["eval"] += time.perf_counter() - start
        self._log({f"eval/{k}": v for k, v in self.last_eval.items()}, self.counters.env_steps)

    def _log_train(self, stats: dict[str, list[torch.Tensor]], timer: dict[str, float]) -> None:
        c = self.counters
        values = {name: torch.stack(v).float().mean().item() for name, v in stats.items() if v}
        values["train/epsilon"] = float(self.epsilon.eps)
        values["train/episodes"] = c.episodes
        values["train/updates"] = c.updates
        values["train/replay_episodes"] = len(self.replay)
        if self.episodic is not None:
            values.update(self.episodic.statistics())
        elapsed = sum(timer.values())
        values.update({f"time/{k}_s": v for k, v in timer.items()})
        if elapsed > 0:  # steps of this session (a resumed run starts its clock again)
            values["time/env_steps_per_s"] = (c.env_steps - self._session_start_steps) / elapsed
        self._log(values, c.env_steps)

    def _log(self, values: dict[str, float], step: int) -> None:
        """Log and count the rows of each metric, so that a resume can drop rows logged after its checkpoint."""
        log_scalars(self.logger, values, step)
        for name in values:
            self._log_rows[name] = self._log_rows.get(name, 0) + 1

    def _progress_bar(self):
        from tqdm.auto import tqdm

        return tqdm(
            total=self.cfg.train.total_env_steps,
            initial=self.counters.env_steps,
            unit="step",
            unit_scale=True,
            dynamic_ncols=True,
            mininterval=1.0,
            disable=not self.cfg.logger.progress_bar,
            desc=f"{self.cfg.algo.name} {self.env_config.name}",
        )

    def _postfix(self) -> dict[str, str]:
        post = {"eps": f"{float(self.epsilon.eps):.3f}"}
        if self.last_eval:
            post["eval_reward"] = f"{self.last_eval['episode_reward']:.1f}"
        return post

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self, replay_inline: bool = True) -> dict[str, Any]:
        """The whole run; the replay's episodes inline, or (``replay_inline=False``) the manifest of the
        block files that :meth:`save` writes for ``last.pt``."""
        state = {
            "config": to_container(self.cfg),
            "fingerprint": self.fingerprint(),
            "logs": {"rows": dict(self._log_rows)},
            "counters": asdict(self.counters),
            "learner": self.learner.state_dict(),
            "last_eval": dict(self.last_eval),
            "rng": {"torch": torch.get_rng_state()},
        }
        if torch.cuda.is_available():
            state["rng"]["cuda"] = torch.cuda.get_rng_state_all()
        if self.cfg.train.save_replay:
            if replay_inline:
                state["replay"] = replay_state_dict(self.replay)
            else:
                state["replay_blocks"] = self.replay_store.save(self.replay)
        if self.episodic is not None:
            state["episodic"] = self.episodic.state_dict()
        return state

    def fingerprint(
        self, config: dict[str, Any] | None = None, learner: dict[str, Any] | None = None
    ) -> dict:
        """What a checkpoint must share with this run (:func:`mcrs.experiment.rundir.fingerprint`): of this
        run, or of a checkpoint's ``config`` and ``learner`` state (checkpoints written before fingerprints)."""
        from mcrs.train import RESUME_MUTABLE

        if learner is None:
            learner = {"agent": self.learner.agent.state_dict(), "mixer": self.learner.mixer.state_dict()}
        config = to_container(self.cfg) if config is None else config
        networks = {name: learner[name] for name in ("agent", "mixer") if name in learner}
        return fingerprint(config, networks, ckpt.VERSION, RESUME_MUTABLE)

    def save(self, name: str = ckpt.LAST) -> Path:
        """Atomically write the full state (``checkpoints/last.pt``) and the weights at this step.

        An I/O error (a full disk, a read-only directory) stops the run in one line; the atomic write
        leaves the previous checkpoint as it was and no temporary behind. ``last.pt`` names the replay's
        block files (only the changed blocks are written); any other name (``last_good.pt``) carries the
        episodes inline, so it stays whole whatever later saves delete.
        """
        target = ckpt.checkpoint_path(self.run_dir, name)
        with io_errors(f"write checkpoint {target}", self._intact()):
            path = self._save(name)
        if name == ckpt.LAST:
            self._saved_steps = self.counters.env_steps
        return path

    def _intact(self) -> str:
        """What survives an I/O error: the checkpoint a resume would start from."""
        last = ckpt.checkpoint_path(self.run_dir)
        if not last.is_file():
            return "; no checkpoint had been written yet"
        return f"; the last checkpoint {last} is intact: free space or fix the directory, then resume={self.run_dir}"

    def _save(self, name: str) -> Path:
        last = name == ckpt.LAST
        path = ckpt.save_atomic(
            self.state_dict(replay_inline=not last), ckpt.checkpoint_path(self.run_dir, name)
        )
        if last:
            self.replay_store.commit()
            self._last_save = time.monotonic()
            weights = {
                "config": to_container(self.cfg),
                "fingerprint": self.fingerprint(),
                "counters": asdict(self.counters),
                "learner": {
                    "agent": self.learner.agent.state_dict(),
                    "mixer": self.learner.mixer.state_dict(),
                },
            }
            ckpt.save_atomic(
                weights, ckpt.checkpoint_path(self.run_dir, f"model_{self.counters.env_steps:09d}.pt")
            )
        return path

    def _load(self, path: Path) -> None:
        state = ckpt.load(path, map_location=self.device)
        saved = state.get("fingerprint")
        if saved is None:  # written before fingerprints: derived from the config and weights it holds
            saved = self.fingerprint(state.get("config", {}), state.get("learner", {}))
        difference = first_difference(saved, self.fingerprint())
        if difference is not None:
            raise ckpt.CheckpointError(f"{path} does not belong to this run: {difference}")
        if "replay" not in state and "replay_blocks" not in state:
            raise ckpt.CheckpointError(
                f"{path} has no replay buffer (train.save_replay=false): it holds weights, not a resumable run"
            )
        self._resume_rng = state["rng"]  # restored last, once everything is built (not the whole state:
        # it holds a copy of the replay buffer)
        try:
            self.learner.load_state_dict(state["learner"])
            if "replay_blocks" in state:
                self.replay_store.load(self.replay, state["replay_blocks"])
            else:  # the episodes inline (checkpoints written before the block files, last_good.pt)
                load_replay_state_dict(self.replay, state["replay"])
            if self.episodic is not None:
                if "episodic" not in state:
                    raise ckpt.CheckpointError(f"{path} has no episodic memory, but this run's algo uses one")
                self.episodic.load_state_dict(state["episodic"])
            self.counters = Counters(**state["counters"])
        except (
            KeyError,
            TypeError,
            ValueError,
            RuntimeError,
        ) as error:  # a fingerprint cannot see everything
            if isinstance(error, ckpt.CheckpointError):
                raise
            first = (str(error).strip().splitlines() or [type(error).__name__])[0]
            raise ckpt.CheckpointError(f"{path} cannot be loaded into this run: {first}") from None
        self.last_eval = dict(state.get("last_eval", {}))
        self.epsilon.set_env_steps(self.counters.env_steps)
        rows = state.get("logs", {}).get("rows")
        with io_errors(f"rewrite the logs of {self.run_dir}"):  # rows logged after the checkpoint go
            self._log_rows = truncate_csv_logs(self.run_dir, rows, self.counters.env_steps)
