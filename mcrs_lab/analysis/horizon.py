"""The horizon gap: how far the TD target and the episodic memory's target disagree, step by step.

Every MCRS episode ends by the time limit T. The memory stores returns cut at T (``H(s_T) = 0``); the TD
target ``r_t + gamma * Q_tot^-(s_{t+1})`` bootstraps from ``s_T`` under ``algo.time_limit=bootstrap``
and stops there under ``terminal``. This tool reads a finished (or stopped) run's last checkpoint, takes
its newest replay episodes and prints, by time step, the mean of

- ``Q_tot^-(s_{t+1}) - H_{t+1}``: the target network's value against the return the memory would store
  (this episode's discounted return cut at T; the memory keeps the highest such return per state),
- ``gamma * (Q_tot^-(s_{t+1}) - H_{t+1})`` under the run's convention: the gap between the TD target and
  the memory's one-step target ``r_t + gamma * H(s_{t+1})`` (eq. 32), 0 at the last step under ``terminal``.

    python -m mcrs_lab.analysis.horizon outputs/map20/qmix/<run> [--episodes 256]

docs/MEMORY.md ("The horizon") shows the figures and the choice they support.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from omegaconf import OmegaConf
from tensordict import TensorDictBase
from torchrl.objectives.value.functional import reward2go

from mcrs.experiment.config import ConfigError, as_typed, validate
from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.run.history import current_config
from mcrs.experiment.run.replay_store import ReplayStore
from mcrs.experiment.training.learner import Learner
from mcrs.experiment.training.replay import make_episode_buffer

#: Time steps shown one by one at the end of the episode (the rest in buckets of ten).
LAST_STEPS = 5


def cut_returns(reward: torch.Tensor, gamma: float) -> torch.Tensor:
    """``[B, T+1]`` discounted returns from every state, cut at T (``H[:, T] = 0``), of rewards ``[B, T]``
    (TorchRL's ``reward2go`` with the episode ending at T)."""
    done = torch.zeros_like(reward, dtype=torch.bool)
    done[:, -1] = True
    returns = reward2go(reward.unsqueeze(-1), done.unsqueeze(-1), gamma, time_dim=-2).squeeze(-1)
    return torch.cat([returns, returns.new_zeros(returns.shape[0], 1)], dim=1)


def horizon_gaps(
    learner: Learner, episodes: TensorDictBase, gamma: float, terminal: bool
) -> dict[str, torch.Tensor]:
    """Per time step ``t`` (``[T]``): ``value_gap`` = mean of ``Q_tot^-(s_{t+1}) - H_{t+1}``, and
    ``target_gap`` = TD target minus memory target under the convention (``terminal``: no bootstrap at T)."""
    reward = episodes.get("reward")[:, :-1, 0]  # [B, T]: whole episodes, every row filled
    # [B, T]: Q_tot^-(s_{t+1}), in the env's units (the learner's are algo.reward_scale times those)
    next_value = learner.loss.bootstrap_values(episodes)[:, 1:, 0] / learner.loss.reward_scale
    returns = cut_returns(reward, gamma)[:, 1:]  # [B, T]: H_{t+1}, 0 at t = T - 1
    value_gap = next_value - returns
    bootstrapped = next_value.clone()
    if terminal:
        bootstrapped[:, -1] = 0.0
    target_gap = gamma * (bootstrapped - returns)
    return {"value_gap": value_gap.mean(0), "target_gap": target_gap.mean(0)}


def load_run(run_dir: Path, device: str = "cpu") -> tuple[Learner, TensorDictBase, object]:
    """The run's learner (from ``checkpoints/last.pt``), its replay episodes, and its typed config."""
    saved = OmegaConf.to_container(OmegaConf.load(run_dir / "config.yaml"), resolve=True)
    cfg = as_typed(OmegaConf.create(current_config(saved)))
    env_config = validate(cfg).replace(device=device)
    learner = Learner(cfg.algo, cfg.model, cfg.train, env_config, torch.device(device))
    path = ckpt.checkpoint_path(run_dir)
    state = ckpt.refuse_pre_release(ckpt.load(path, map_location=device), path)
    learner.load_state_dict(state["learner"])
    replay = make_episode_buffer(cfg.train.replay_episodes, cfg.train.batch_episodes, device=device)
    if "replay_blocks" not in state:
        raise ckpt.CheckpointError(
            f"{run_dir}: its last.pt carries no replay blocks (train.save_replay=false)"
        )
    ReplayStore(ckpt.checkpoint_path(run_dir).parent).load(replay, state["replay_blocks"])
    # Oldest first: once the ring buffer has wrapped, the oldest episode sits at the writer's cursor.
    n = len(replay)
    start = int(replay.writer.state_dict()["_cursor"]) % n if n == replay.storage.max_size else 0
    return learner, replay.storage.get((torch.arange(n) + start) % n), cfg


def table(gaps: dict[str, torch.Tensor]) -> str:
    """Markdown rows: steps in buckets of ten, then the last :data:`LAST_STEPS` steps one by one."""
    T = gaps["value_gap"].shape[0]
    spans = [(a, min(a + 10, T - LAST_STEPS)) for a in range(0, T - LAST_STEPS, 10)]
    spans += [(t, t + 1) for t in range(T - LAST_STEPS, T)]
    lines = ["| step t | Q_tot^-(s_t+1) - H_t+1 | TD target - memory target |", "|---|---:|---:|"]
    for a, b in spans:
        label = f"{a}" if b == a + 1 else f"{a}-{b - 1}"
        value, target = gaps["value_gap"][a:b].mean().item(), gaps["target_gap"][a:b].mean().item()
        lines.append(f"| {label} | {value:.2f} | {target:.2f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m mcrs_lab.analysis.horizon", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument(
        "run", type=Path, help="an mcrs-train run directory (config.yaml, checkpoints/last.pt)"
    )
    parser.add_argument("--episodes", type=int, default=256, help="the newest replay episodes to read")
    args = parser.parse_args(argv)
    if args.episodes < 1:
        raise SystemExit(f"horizon: error: --episodes={args.episodes}: must be >= 1")
    if not (args.run / "config.yaml").is_file() or not ckpt.checkpoint_path(args.run).is_file():
        raise SystemExit(
            f"horizon: error: {args.run}: not an mcrs-train run (needs config.yaml and checkpoints/last.pt)"
        )
    try:
        learner, episodes, cfg = load_run(args.run)
    except (ConfigError, ckpt.CheckpointError, ValueError) as error:
        raise SystemExit(f"horizon: error: {args.run}: {error}") from None
    if not bool(episodes.get("filled")[:, :-1].all()):
        raise SystemExit(
            "horizon: error: the replay holds episodes cut short: this tool reads whole episodes"
        )
    terminal = str(cfg.algo.time_limit) == "terminal"
    newest = episodes[-args.episodes :]
    gaps = horizon_gaps(learner, newest, cfg.algo.gamma, terminal)
    print(
        f"{args.run}: {cfg.algo.name} on {cfg.env.name}, algo.time_limit={cfg.algo.time_limit}, "
        f"gamma={cfg.algo.gamma}, the newest {newest.batch_size[0]} replay episodes"
    )
    print(table(gaps))
    return 0


if __name__ == "__main__":
    sys.exit(main())
