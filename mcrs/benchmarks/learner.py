"""Learner benchmark (``mcrs-bench-learner``, ``python -m mcrs.benchmarks.learner``).

Why: the TorchRL stack (replay buffer, ``LossModule``, functional target parameters) must not make a
learner update much slower than the plain PyTorch a pymarl user would write, and a whole training run must
fit the design's time budget. This prints, at the pymarl preset (QMIX, 32-episode batches, RMSprop,
double Q, one-step targets), with PASS/FAIL:

* seconds per learner update of our :class:`~mcrs.experiment.trainer.Learner` (a batch sampled from our
  TorchRL episode buffer, then ``Learner.update``) and of a minimal plain-PyTorch reference learner written
  here (same networks, no TorchRL, no tensordict, episodes sampled from preallocated tensors with
  ``torch.randint``); goal: ours <= 1.15x the reference;
* env-steps/s of the real training loop (:class:`~mcrs.experiment.trainer.Trainer`) in steady state, and
  the hours it extrapolates to for 2M env steps; goal on map20: <= 1.25 h.

Fairness: the reference starts from our learner's weights (state dicts), and the two losses are checked
once to agree (to 1e-5 relative) on the same batch, before and after one update of each; a reference that
computed something else would not be a reference. The two learners are timed alternately (A/B, then B/A)
in the same process so that machine drift hits both, and the ratio is the median of the per-pair ratios.
The replay holds synthetic but valid episodes in the episode layout (random observations and states,
random masks with at least one allowed action, actions drawn among the allowed ones): the cost of an
update does not depend on the values.
"""

from __future__ import annotations

import argparse
import copy
import gc
import os
import shlex
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from omegaconf import DictConfig
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torch.nn import functional as F

from mcrs.benchmarks.common import benchmark_process, load_average, pass_fail
from mcrs.env.config import SCENARIOS, EnvConfig, from_mapping
from mcrs.env.core import N_ACTIONS

GOAL_RATIO = 1.15  # ours / reference, seconds per update
GOAL_MAP = "map20"
GOAL_HOURS = 1.25  # wall-clock for GOAL_STEPS env steps on GOAL_MAP
GOAL_STEPS = 2_000_000
AGREE_RTOL = 1e-5
WARMUP = 3  # untimed updates of each learner before the timed ones
REPLAY_EPISODES = 256  # synthetic episodes in each replay (sampling cost hardly depends on it)
NEVER = 10**12  # an interval the short loop run never reaches
DEFAULT_UPDATES = 30
DEFAULT_LOOP_STEPS = 20_000
# --quick: tiny episodes and batches, for a smoke test of the whole command in seconds.
QUICK_OVERRIDES = (
    "env.max_steps=6",
    "train.batch_episodes=4",
    "train.num_envs=4",
    "train.replay_episodes=16",
    "train.eval_episodes=2",
)
QUICK_REPLAY_EPISODES = 16
QUICK_NOTE = "\n--quick: 4-episode batches of 6-step episodes instead, goals not judged"
QUICK_UPDATES = 3
NEG_INF = -1e10


# ---------------------------------------------------------------------------------------- the config
def compose_config(map_name: str, quick: bool, extra: Sequence[str] = (), algo: str = "qmix") -> DictConfig:
    """The real ``mcrs-train`` config (pymarl preset, ``algo``) for ``map_name``, composed in-process."""
    from hydra import compose, initialize_config_dir

    from mcrs.train import CONFIG_DIR  # also registers the structured config schema

    overrides = [
        f"env={map_name}",
        "preset=pymarl",
        f"algo={algo}",
        *(QUICK_OVERRIDES if quick else ()),
        *extra,
    ]
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return compose(config_name="config", overrides=overrides)


# ---------------------------------------------------------------------------------------- synthetic episodes
def synthetic_episodes(n: int, env_config: EnvConfig, generator: torch.Generator) -> TensorDict:
    """``n`` valid episodes in the episode layout ``[n, T + 1]`` read by ``ValueFactorisationLoss``.

    Every step allows at least one action and every action taken is allowed; each episode ends at step T
    (``done``), and about a quarter end in a terminal state (no bootstrap), so that the agreement check
    also covers the ``terminated`` branch (our environment itself only truncates).
    """
    T, N, A = env_config.max_steps, env_config.n_uavs, N_ACTIONS
    shape = (n, T + 1)
    mask = torch.rand(*shape, N, A, generator=generator) < 0.6
    forced = torch.randint(A, (*shape, N, 1), generator=generator)
    mask.scatter_(-1, forced, True)
    noise = torch.rand(*shape, N, A, generator=generator).masked_fill(~mask, -1.0)
    action = noise.argmax(-1)
    action[:, -1] = 0  # padding row, as episodes_from_rollout writes it
    reward = torch.randn(*shape, 1, generator=generator)
    reward[:, -1] = 0.0
    done = torch.zeros(*shape, 1, dtype=torch.bool)
    done[:, T - 1 :] = True
    terminated = torch.zeros(*shape, 1, dtype=torch.bool)
    terminated[:, T - 1, 0] = torch.rand(n, generator=generator) < 0.25
    filled = torch.ones(*shape, dtype=torch.bool)
    filled[:, -1] = False
    out = TensorDict(batch_size=list(shape))
    out.set(("agents", "observation"), torch.rand(*shape, N, env_config.obs_dim, generator=generator))
    out.set(("agents", "action_mask"), mask)
    out.set("state", torch.rand(*shape, env_config.state_dim, generator=generator))
    out.set(("agents", "action"), action)
    out.set("reward", reward)
    out.set("done", done)
    out.set("terminated", terminated)
    out.set("filled", filled)
    return out


def as_plain(episodes: TensorDictBase) -> dict[str, torch.Tensor]:
    """The tensors of an episode batch under the reference's flat names (no tensordict beyond here)."""
    return {
        "obs": episodes.get(("agents", "observation")),
        "mask": episodes.get(("agents", "action_mask")),
        "state": episodes.get("state"),
        "action": episodes.get(("agents", "action")),
        "reward": episodes.get("reward"),
        "terminated": episodes.get("terminated"),
        "filled": episodes.get("filled"),
    }


# ---------------------------------------------------------------------------------------- the reference
class ReferenceReplay:
    """Episodes in preallocated plain tensors ``[capacity, T + 1, ...]``; uniform sampling with replacement."""

    def __init__(self, episodes: dict[str, torch.Tensor], batch_size: int) -> None:
        self.data = {k: v.clone() for k, v in episodes.items()}
        self.size = next(iter(self.data.values())).shape[0]
        self.batch_size = batch_size

    def sample(self) -> dict[str, torch.Tensor]:
        idx = torch.randint(self.size, (self.batch_size,))
        return {k: v[idx] for k, v in self.data.items()}


class ReferenceAgent(nn.Module):
    """pymarl's RNN agent: ``Linear(in, H) -> ReLU -> GRU(H) -> Linear(H, A)``, agents folded into the batch."""

    def __init__(self, input_dim: int, hidden_dim: int, n_actions: int) -> None:
        super().__init__()
        self.hidden_dim = hidden_dim
        self.fc1 = nn.Linear(input_dim, hidden_dim)
        self.rnn = nn.GRU(hidden_dim, hidden_dim, batch_first=True)
        self.fc2 = nn.Linear(hidden_dim, n_actions)

    def forward(self, inputs: torch.Tensor) -> torch.Tensor:
        """``inputs [B, T, N, in]`` -> ``q [B, T, N, A]`` from a zero hidden state."""
        B, T, N, _ = inputs.shape
        x = F.relu(self.fc1(inputs)).transpose(1, 2).reshape(B * N, T, self.hidden_dim)
        out, _ = self.rnn(x)
        return self.fc2(out.reshape(B, N, T, self.hidden_dim).transpose(1, 2))


class ReferenceQMixer(nn.Module):
    """pymarl's QMIX mixer: 2-layer hypernetworks, absolute weights, ELU, a V(s) head."""

    def __init__(self, n_agents: int, state_dim: int, embed_dim: int, hypernet_embed: int) -> None:
        super().__init__()
        self.n_agents, self.state_dim, self.embed_dim = n_agents, state_dim, embed_dim
        self.hyper_w_1 = nn.Sequential(
            nn.Linear(state_dim, hypernet_embed), nn.ReLU(), nn.Linear(hypernet_embed, embed_dim * n_agents)
        )
        self.hyper_w_final = nn.Sequential(
            nn.Linear(state_dim, hypernet_embed), nn.ReLU(), nn.Linear(hypernet_embed, embed_dim)
        )
        self.hyper_b_1 = nn.Linear(state_dim, embed_dim)
        self.V = nn.Sequential(nn.Linear(state_dim, embed_dim), nn.ReLU(), nn.Linear(embed_dim, 1))

    def forward(self, qs: torch.Tensor, states: torch.Tensor) -> torch.Tensor:
        """``qs [B, T, N]``, ``states [B, T, S]`` -> ``q_tot [B, T, 1]``."""
        B, T = qs.shape[:2]
        s = states.reshape(-1, self.state_dim)
        q = qs.reshape(-1, 1, self.n_agents)
        w1 = self.hyper_w_1(s).abs().view(-1, self.n_agents, self.embed_dim)
        b1 = self.hyper_b_1(s).view(-1, 1, self.embed_dim)
        hidden = F.elu(torch.bmm(q, w1) + b1)
        w_final = self.hyper_w_final(s).abs().view(-1, self.embed_dim, 1)
        v = self.V(s).view(-1, 1, 1)
        return (torch.bmm(hidden, w_final) + v).view(B, T, 1)


class ReferenceLearner:
    """The update a pymarl user writes by hand: double-Q one-step TD loss of QMIX, RMSprop, grad clipping."""

    def __init__(self, cfg: DictConfig, env_config: EnvConfig) -> None:
        a, m, t = cfg.algo, cfg.model, cfg.train
        if (
            a.mixer != "qmix"
            or a.hypernet_layers != 2
            or a.td_lambda != 0.0
            or not (m.agent_id and m.last_action)
        ):
            raise ValueError(
                "the reference learner is QMIX with 2-layer hypernets, one-step targets, id and last action"
            )
        self.n_agents, self.n_actions = env_config.n_uavs, N_ACTIONS
        input_dim = env_config.obs_dim + N_ACTIONS + env_config.n_uavs
        self.agent = ReferenceAgent(input_dim, m.hidden_dim, N_ACTIONS)
        self.mixer = ReferenceQMixer(
            env_config.n_uavs, env_config.state_dim, a.mixing_embed_dim, a.hypernet_embed
        )
        self.target_agent = copy.deepcopy(self.agent)
        self.target_mixer = copy.deepcopy(self.mixer)
        self.gamma, self.double_q, self.grad_clip = float(a.gamma), bool(a.double_q), float(t.grad_clip)
        self.params = [*self.agent.parameters(), *self.mixer.parameters()]
        self.optimizer = torch.optim.RMSprop(self.params, lr=t.lr, alpha=t.rmsprop_alpha, eps=t.optim_eps)

    def load_weights(self, state: dict[str, Any]) -> None:
        """Online and target weights from :meth:`Learner.state_dict` (same parameter names)."""
        self.agent.load_state_dict(state["agent"])
        self.mixer.load_state_dict(state["mixer"])
        self.target_agent.load_state_dict(state["target_agent"])
        self.target_mixer.load_state_dict(state["target_mixer"])

    def build_inputs(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Observation, one-hot last action (zeros at t=0) and one-hot agent id: ``[B, T+1, N, in]``."""
        B, T1, N, _ = obs.shape
        last_action = torch.zeros(B, T1, N, self.n_actions, dtype=obs.dtype)
        last_action[:, 1:] = F.one_hot(action[:, :-1], self.n_actions).to(obs.dtype)
        ids = torch.eye(N, dtype=obs.dtype).expand(B, T1, N, N)
        return torch.cat([obs, last_action, ids], dim=-1)

    def loss(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        inputs = self.build_inputs(batch["obs"], batch["action"])
        actions, mask = batch["action"][:, :-1], batch["mask"]
        q = self.agent(inputs)  # [B, T+1, N, A]
        chosen = q[:, :-1].gather(-1, actions.unsqueeze(-1)).squeeze(-1)
        q_tot = self.mixer(chosen, batch["state"][:, :-1])
        with torch.no_grad():
            target_q = self.target_agent(inputs)[:, 1:].masked_fill(~mask[:, 1:], NEG_INF)
            chooser = q.detach()[:, 1:].masked_fill(~mask[:, 1:], NEG_INF) if self.double_q else target_q
            next_chosen = target_q.gather(-1, chooser.argmax(-1, keepdim=True)).squeeze(-1)
            next_q_tot = self.target_mixer(next_chosen, batch["state"][:, 1:])
            not_terminal = 1.0 - batch["terminated"][:, :-1].to(q_tot.dtype)
            y = batch["reward"][:, :-1] + self.gamma * not_terminal * next_q_tot
        weight = batch["filled"][:, :-1].unsqueeze(-1).to(q_tot.dtype)
        return ((q_tot - y) * weight).pow(2).sum() / weight.sum()

    def update(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        loss = self.loss(batch)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        nn.utils.clip_grad_norm_(self.params, self.grad_clip)
        self.optimizer.step()
        return loss.detach()


# ---------------------------------------------------------------------------------------- (a) - (c)
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


@dataclass
class Agreement:
    """The two learners' losses on the same batch, before and after one update of each."""

    ours: tuple[float, float]
    reference: tuple[float, float]

    @property
    def rel_diffs(self) -> tuple[float, ...]:
        return tuple(abs(o - r) / max(abs(r), 1e-12) for o, r in zip(self.ours, self.reference, strict=True))

    @property
    def agree(self) -> bool:
        return all(d <= AGREE_RTOL for d in self.rel_diffs)


def check_agreement(learner: Any, reference: ReferenceLearner, replay: Any) -> Agreement:
    """Loss of both on one batch; one update of both on that batch; loss of both on a second batch.

    The second comparison has target != online networks (so double-Q matters) and follows an optimiser
    step and gradient clipping of each, so it also checks that the updates are the same.
    """
    ours, ref = [], []
    first = replay.sample()
    with torch.no_grad():
        ours.append(learner.loss(first)["loss"].item())
        ref.append(reference.loss(as_plain(first)).item())
    learner.update(first, 0)
    reference.update(as_plain(first))
    second = replay.sample()
    with torch.no_grad():
        ours.append(learner.loss(second)["loss"].item())
        ref.append(reference.loss(as_plain(second)).item())
    return Agreement((ours[0], ours[1]), (ref[0], ref[1]))


def _timed(step: Callable[[], Any], update: Callable[[Any], Any]) -> tuple[float, float]:
    start = time.perf_counter()
    batch = step()
    mid = time.perf_counter()
    update(batch)
    return mid - start, time.perf_counter() - mid


def measure_updates(map_name: str, quick: bool, updates: int) -> tuple[EnvConfig, Agreement, UpdateTimes]:
    """Build both learners from the same weights, check their losses agree, then time them alternately."""
    from mcrs.experiment.learner import Learner
    from mcrs.experiment.replay import make_episode_buffer

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


# ---------------------------------------------------------------------------------------- (d) the loop
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
    """Run the real :class:`Trainer` and time its steady state from its own counters.

    The run evaluates only at its start and end (``eval_interval`` out of reach) and writes no checkpoint
    on the way; evaluations are timed on their own and added back in the extrapolation at the preset's
    interval. The window starts when the first collector batch is stored, so it leaves out start-up (the
    first batch, the first update, allocation of the replay) and it contains whole iterations: the updates
    after a batch, logging, and the next collection.
    """
    from mcrs.experiment.experiment import Experiment

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
        extend, update, evaluate = trainer.replay.extend, trainer._update, trainer._evaluate

        def marked_extend(*args: Any, **kwargs: Any) -> Any:
            marks.append((time.perf_counter(), c.env_steps, c.updates, spent[0]))
            return extend(*args, **kwargs)

        def timed_update() -> dict[str, torch.Tensor]:
            begin = time.perf_counter()
            try:
                return update()
            finally:
                spent[0] += time.perf_counter() - begin

        def timed_evaluate(timer: dict[str, float]) -> None:
            begin = time.perf_counter()
            evaluate(timer)
            evals.append(time.perf_counter() - begin)

        trainer.replay.extend = marked_extend  # instance attributes: the loop calls them through self
        trainer._update = timed_update
        trainer._evaluate = timed_evaluate
        trainer.train()
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


# ---------------------------------------------------------------------------------------- the launcher
_LAUNCHER_WORKER = (
    "import json, sys, torch\n"
    "from mcrs.benchmarks.learner import measure_loop\n"
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


# ---------------------------------------------------------------------------------------- the command


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


def _parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="mcrs-bench-learner",
        description="Seconds per learner update (ours vs a plain-PyTorch reference) and training-loop "
        "throughput at the pymarl preset, with goals.",
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
    parser.add_argument("--threads", type=int, default=0, help="torch intra-op threads (0: torch's default)")
    parser.add_argument(
        "--launcher-steps",
        type=int,
        default=0,
        help="env steps of each run of the launcher comparison (one 2-thread run, then two 1-thread runs "
        "side by side) on the first map; 0 skips it",
    )
    parser.add_argument("--quick", action="store_true", help="tiny episodes and batches: a smoke test")
    args = parser.parse_args(argv)
    if args.launcher_steps < 0:
        parser.error(f"--launcher-steps must be >= 0, got {args.launcher_steps}")
    if args.updates is None:
        args.updates = QUICK_UPDATES if args.quick else DEFAULT_UPDATES
    if args.loop_steps is None:
        args.loop_steps = 1 if args.quick else DEFAULT_LOOP_STEPS  # --quick: the 4-batch minimum
    if args.updates < 1:
        parser.error(f"--updates must be >= 1, got {args.updates}")
    if args.loop_steps < 0:
        parser.error(f"--loop-steps must be >= 0, got {args.loop_steps}")
    if args.threads < 0:
        parser.error(f"--threads must be >= 0, got {args.threads}")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark and print the update table, the ratios, the loop figures and the goals."""
    command = shlex.join(["mcrs-bench-learner", *(sys.argv[1:] if argv is None else argv)])
    args = _parse_args(argv)
    with benchmark_process(args.threads):
        _run(args, command)
    return 0


def _run(args: argparse.Namespace, command: str) -> None:
    judged = not args.quick
    goals: list[str] = []
    print(
        f"MCRS learner benchmark: device=cpu, torch threads={torch.get_num_threads()}, cpus={os.cpu_count()}, "
        f"load average {load_average()}\n"
        f"command: {command}\n"
        "preset pymarl: QMIX (2-layer hypernets), 32-episode batches, RMSprop lr 5e-4, double Q, one-step "
        f"targets, grad clip 10{QUICK_NOTE if args.quick else ''}\n"
        f"update rows: median of {args.updates} timed updates (sample a batch + gradient step) after {WARMUP} "
        f"warm-up, ours and reference alternated; replay of "
        f"{QUICK_REPLAY_EPISODES if args.quick else REPLAY_EPISODES} synthetic episodes each",
        flush=True,
    )
    for name in args.maps:
        env_config, agreement, times = measure_updates(name, args.quick, args.updates)
        diffs = ", ".join(f"{d:.1e}" for d in agreement.rel_diffs)
        print(
            f"\n{name}: {env_config.n_uavs} agents, T={env_config.max_steps}, obs {env_config.obs_dim}, "
            f"state {env_config.state_dim}\n"
            f"losses agree: {'yes' if agreement.agree else 'no'} (ours {agreement.ours[0]:.6g} / "
            f"{agreement.ours[1]:.6g}, reference {agreement.reference[0]:.6g} / {agreement.reference[1]:.6g} "
            f"before / after one update; relative differences {diffs}; tolerance {AGREE_RTOL:g})",
            flush=True,
        )
        print(f"{'map':<6} {'learner':<10} {'sample ms':>10} {'update ms':>10} {'total ms':>10}")
        for label, sample, update in (
            ("ours", times.ours_sample, times.ours_update),
            ("reference", times.ref_sample, times.ref_update),
        ):
            print(
                f"{name:<6} {label:<10} {sample * 1e3:>10.2f} {update * 1e3:>10.2f} {(sample + update) * 1e3:>10.2f}"
            )
        verdict = (
            pass_fail(times.ratio <= GOAL_RATIO and agreement.agree) if judged else "not judged (--quick)"
        )
        print(
            f"ratio {name}: ours / reference = {times.ratio:.2f}x per update (median of {times.pairs} "
            f"interleaved pairs; goal <= {GOAL_RATIO:g}x: {verdict})",
            flush=True,
        )
        if judged:
            note = "" if agreement.agree else " (losses disagree: the comparison is void)"
            goals.append(
                f"{name} update ours / reference <= {GOAL_RATIO:g}x: {times.ratio:.2f}x {verdict}{note}"
            )

    if args.loop_steps:
        print(
            "\ncollector step (env + recurrent policy + exploration), 1 env vs 32 envs at once:", flush=True
        )
        for name in args.maps:
            env_config = from_mapping(compose_config(name, args.quick).env)
            one, many = (collector_step_seconds(env_config, e, 1 if args.quick else 3) for e in (1, 32))
            print(
                f"{name:<6} 1 env {one * 1e3:.2f} ms/step, 32 envs {many * 1e3:.2f} ms/step "
                f"({many / 32 * 1e3:.3f} ms per env step)",
                flush=True,
            )
        print(
            "\ntraining loop (the real Trainer, pymarl preset, csv logger, no progress bar, no checkpoints): "
            "steady state from the end of the first collector batch to the end of the last;\n"
            "evaluation only at the start and end of the run, timed on its own and added back at the "
            "preset's interval; checkpoints (every 100,000 steps, with the replay) not included",
            flush=True,
        )
        header = (
            f"{'map':<6} {'window steps':>12} {'env-steps/s':>12} {'s/update':>9} {'eval s':>7} "
            f"{'2M h (loop)':>11} {'2M h (+eval)':>12}"
        )
        printed = False
        for name in args.maps:
            r = measure_loop(name, args.quick, args.loop_steps, args.threads)
            if not printed:
                print(header)
                printed = True
            per_update = r.update_seconds / r.updates if r.updates else float("nan")
            hours, hours_eval = r.hours(GOAL_STEPS, False), r.hours(GOAL_STEPS, True)
            print(
                f"{name:<6} {r.env_steps:>12,} {r.env_steps_per_s:>12,.0f} {per_update:>9.4f} "
                f"{r.eval_seconds:>7.2f} {hours:>11.2f} {hours_eval:>12.2f}   "
                f"(run of {r.total_steps:,} steps, {r.updates} updates in the window, {r.wall_seconds:.0f} s wall; "
                f"eval: {r.eval_episodes} episodes every {r.eval_interval:,} steps)",
                flush=True,
            )
            if name == GOAL_MAP and judged:
                goals.append(
                    f"{name} {GOAL_STEPS / 1e6:g}M env steps <= {GOAL_HOURS:g} h: {hours_eval:.2f} h "
                    f"{pass_fail(hours_eval <= GOAL_HOURS)} (loop {hours:.2f} h + evaluation every "
                    f"{r.eval_interval:,} steps; checkpoints not included)"
                )
    if args.launcher_steps:
        name = args.maps[0]
        print(
            f"\nlauncher ({name}, the real Trainer as above, each run in its own process): one run with 2 torch "
            "threads alone, then two runs with 1 thread each side by side",
            flush=True,
        )
        one, pair = launcher_rates(name, args.quick, args.launcher_steps)
        print(
            f"one 2-thread run: {one:,.0f} env-steps/s; two 1-thread runs: {pair[0]:,.0f} + {pair[1]:,.0f} = "
            f"{sum(pair):,.0f} env-steps/s (load average {load_average()})\n"
            f"two 1-thread runs vs one 2-thread run: {sum(pair) / one:.2f}x (aggregate env-steps/s; above 1: "
            "the local2 launcher's two 1-thread runs use the cores better)",
            flush=True,
        )
    if judged:
        if GOAL_MAP not in args.maps or not args.loop_steps:
            goals.append(
                f"{GOAL_MAP} {GOAL_STEPS / 1e6:g}M env steps <= {GOAL_HOURS:g} h: n/a (loop not measured)"
            )
        print("\ngoals:", flush=True)
        for line in goals:
            print(f"  {line}", flush=True)


if __name__ == "__main__":
    raise SystemExit(main())
