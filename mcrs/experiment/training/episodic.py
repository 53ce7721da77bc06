"""The episodic memory of a run as a callback: D_E, the embedding phi and its training (paper Algorithm 2,
lines 4-11)::

    after each collection:        insert the new episodes, s_0 .. s_T, into D_E (Algorithm 1)
    every t_emb env steps:        train phi on a sample of D_E (eq. 31), then re-embed every stored state
    before every learner update:  write H(phi(s_{t+1})) into the sampled batch (memory_return, memory_hit,
                                  memory_ratio)

It is built from ``algo.memory`` and the algorithm's incentive strategy (:mod:`mcrs.objectives.incentive`).
All of it is in every checkpoint, so a resumed run continues with the same memory.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase

from mcrs.env.config import EnvConfig
from mcrs.experiment.schema import Config
from mcrs.experiment.training.callbacks import Callback, Scalars
from mcrs.memory.codec import StateCodec
from mcrs.memory.delta import match_tolerance
from mcrs.memory.episodic import EpisodicMemory
from mcrs.memory.transform import EpisodicLookup
from mcrs.models.embedding_training import EmbeddingTrainer
from mcrs.models.embeddings import make_embedding
from mcrs.objectives.incentive import Incentive, make_incentive


def build_embedding(cfg: Config, env_config: EnvConfig):
    """phi for this config and map; raises ValueError when it does not fit the map."""
    mem = cfg.algo.memory
    return make_embedding(
        str(mem.embedding),
        env_config.state_dim,
        (env_config.width, env_config.height),
        key_dim=mem.key_dim,
        hidden_dim=mem.hidden_dim,
        cnn_channels=tuple(mem.cnn_channels),
        seed=int(cfg.seed),
    )


class EpisodicMemoryCallback(Callback):
    """D_E with its embedding and the embedding's trainer, for one run; ``incentive`` defaults to
    ``algo.incentive``'s."""

    name = "memory"

    def __init__(
        self, cfg: Config, env_config: EnvConfig, device: torch.device, incentive: Incentive | None = None
    ) -> None:
        mem, a = cfg.algo.memory, cfg.algo
        if incentive is None:
            incentive = make_incentive(str(a.incentive), a.incentive_threshold)
        self.incentive = incentive
        self.max_steps = env_config.max_steps
        self.embedding = build_embedding(cfg, env_config).to(device)
        self.tolerance = match_tolerance(mem.delta, str(mem.delta_rule), str(mem.neighbourhood), mem.key_dim)
        self.memory = EpisodicMemory(
            self.embedding,
            StateCodec(env_config),
            capacity=mem.capacity,
            tolerance=self.tolerance,
            gamma=a.gamma,
            max_steps=env_config.max_steps,
            track_desirability=incentive.tracks_desirability,
            device=device,
            shape=str(mem.neighbourhood),
            counter_reset=mem.counter_reset,
        )
        self.trainer = (
            EmbeddingTrainer(
                self.embedding,
                lr=mem.embedding_lr,
                batch_size=mem.embedding_batch,
                samples=mem.embedding_samples,
                state_weight=mem.state_weight,
                grad_clip=mem.embedding_grad_clip,
            )
            if self.embedding.trainable
            else None
        )
        self.interval = int(mem.embedding_interval)
        self.next_embedding = self.interval  # env step of the next training of phi
        self.last_eval_reward: float | None = None  # EMU-change's threshold
        with_ratio = "memory_ratio" in incentive.in_keys
        self.lookup = EpisodicLookup(self.memory, self.max_steps, with_ratio=with_ratio)

    # ------------------------------------------------------------------ hooks
    def on_train_batch(self, batch: TensorDictBase, env_steps: int) -> Scalars:
        """Write the memory's answers for the sampled batch: ``memory_return``, ``memory_hit`` and, when the
        incentive reads it, ``memory_ratio``."""
        self.lookup(batch)
        return {}

    def on_batch_collected(self, batch: TensorDictBase, episode_ids: torch.Tensor) -> Scalars:
        """Algorithm 1 on the new episodes; phi is retrained every t_emb env steps."""
        stats: Scalars = dict(self.insert(batch, episode_ids, self.last_eval_reward))
        env_steps = self.experiment.counters.env_steps
        if env_steps >= self.next_embedding:
            stats.update(self.train_embedding())
            self.next_embedding += self.interval
        return stats

    def on_evaluation_end(self, metrics: dict[str, float]) -> None:
        self.last_eval_reward = metrics.get("episode_reward")

    # ------------------------------------------------------------------ the memory
    def insert(
        self, batch: TensorDictBase, episode: torch.Tensor, last_eval_reward: float | None
    ) -> dict[str, float]:
        """Algorithm 1 on a collector batch ``[E, T]`` of whole episodes; returns diagnostics. The terminal
        states s_T go in too, with H = 0 as EMC stores them, so every episode's last transition has a memory
        to look up."""
        reward = batch.get(("next", "reward"))[..., 0]
        # EMU: desirable episodes reach the incentive's return threshold (None: no incentive, none marked).
        desirable = self.incentive.desirable(reward.sum(-1), last_eval_reward)
        states, counts = (
            torch.cat([batch.get(key), batch.get(("next", key))[:, -1:]], dim=1)
            for key in ("state", "state_counts")
        )
        reward = torch.cat([reward, reward.new_zeros(reward.shape[0], 1)], dim=1)  # R_T = 0
        stats = self.memory.insert(states, counts, reward, desirable, episode)
        out = {f"memory/insert_{k}": float(v) for k, v in vars(stats).items()}
        out["memory/insert_hit_rate"] = stats.hits / max(stats.transitions, 1)
        if desirable is not None:
            out["memory/desirable_episodes"] = float(desirable.float().mean())
        return out

    def train_embedding(self) -> dict[str, float]:
        """Train phi on a sample of D_E, then re-embed every stored state (Algorithm 2, lines 8-11)."""
        if self.trainer is None or len(self.memory) == 0:
            return {}
        stats = self.trainer.fit(self.memory.sample)
        self.memory.refresh_keys()
        return {f"memory/embedding_{k}": float(v) for k, v in stats.items()}

    def statistics(self) -> dict[str, float]:
        """The buffer's scalars, the tolerance and the look-ups' hit rates since the last call."""
        stats = {**self.memory.statistics(), "tolerance": self.tolerance, **self.lookup.pop_statistics()}
        return {f"memory/{k}": float(v) for k, v in stats.items()}

    def state_dict(self) -> dict[str, Any]:
        state: dict[str, Any] = {
            "memory": self.memory.state_dict(),
            "embedding": self.embedding.state_dict(),
            "next_embedding": self.next_embedding,
            "last_eval_reward": self.last_eval_reward,
        }
        if self.trainer is not None:
            state["embedding_trainer"] = self.trainer.state_dict()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.next_embedding = int(state["next_embedding"])
        self.last_eval_reward = state["last_eval_reward"]
        self.embedding.load_state_dict(state["embedding"])
        if self.trainer is not None:
            self.trainer.load_state_dict(state["embedding_trainer"])
        self.memory.load_state_dict(state["memory"])
