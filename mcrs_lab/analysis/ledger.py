"""The reward ledger: where a policy's episode reward goes, term by term, and why it pays its penalties.

For each policy (a heuristic or an ``mcrs-train`` run) it plays the same evaluation episodes as
``mcrs-eval`` (one seeded batch, greedy actions) and sums, per episode,

- the four reward terms r1 (uncertainty), r2 (discovery), r3 (no-fly), r4 (collision);
- r1 reached by a quarter, a half and three quarters of the episode: how fast the map is read;
- the no-fly charges r3 counts, by the UAV's move that caused them: onto a cell no UAV had read yet (the
  charge buys a first reading, worth up to ``m_E`` of uncertainty), onto a cell already read or known (it
  buys little; under ``no_fly_prior=known`` every zone is known), and of those, how many were made while the UAV had an allowed move that r3 does not charge to
  a cell it still held unread (its own m(U) = 1 in its observation): a charge it could have avoided
  without giving up a first reading;
- the moves onto a cell the UAV holds read (its own m(U) < 1) made while an allowed move onto a cell it
  holds unread was at hand, in the first and the second half of the episode: the steps a one-step greedy
  reader would not waste; and the steps with no allowed move onto a cell it holds unread (stranded in
  read ground), by half, with the own m(U) given up on them: the largest own m(U) among the allowed moves
  less that of the move taken, summed.

``--shield`` plays with ``env.no_fly_shield=true`` (the moves r3 would charge masked): what a policy
scores when it cannot enter a zone; ``--uav-shield`` with ``env.uav_shield=true`` (each UAV gives way to
the lower-indexed UAVs in sight): what it scores when it cannot collide. Issue 30 item 4 and
docs/DIAGNOSTICS.md use them.

    python -m mcrs_lab.analysis.ledger --env map20 --policy coverage --policy outputs/<run> [--shield] [--uav-shield]
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from mcrs.env.config import PRESETS, EnvConfig
from mcrs.env.core import MOVES
from mcrs.env.layout import ObservationLayout, StateLayout
from mcrs.env.torchrl_env import MCRSEnv
from mcrs.experiment.run.checkpoint import CheckpointError
from mcrs.experiment.util.tables import markdown
from mcrs.policies import POLICIES, make_policy, policy_env
from mcrs.policies.base import ACTION, ACTION_MASK, OBSERVATION
from mcrs_lab.analysis.env_fields import scenario_with

TERMS = ("r1 uncertainty", "r2 discovery", "r3 no-fly", "r4 collision")
#: Fractions of the episode at which the uncertainty reward r1 gathered so far is reported.
CHECKPOINTS = (0.25, 0.5, 0.75)
#: An own m(U) at or above this is a cell the UAV holds unread (m(U) = 1 exactly in float32).
UNREAD = 1.0 - 1e-6


@dataclass
class Ledger:
    """Per-episode sums ``[K]`` (``terms`` ``[K, 4]``, ``r1_by`` ``[K, len(CHECKPOINTS)]``)."""

    terms: torch.Tensor
    r1_by: torch.Tensor
    charged_first: torch.Tensor  # r3 charges of moves onto a cell no UAV had read
    charged_read: torch.Tensor  # r3 charges of moves onto a cell already read
    charged_avoidable: torch.Tensor  # charges made while an uncharged move to an own-unread cell was allowed
    rereads: torch.Tensor  # [K, 2] moves onto an own-read cell while an own-unread one was allowed, by half
    stranded: torch.Tensor  # [K, 2] (UAV, step)s with no allowed move onto an own-unread cell, by half
    given_up: torch.Tensor  # [K, 2] on those steps, sum of (largest allowed own m(U) - the chosen one's)

    @property
    def reward(self) -> torch.Tensor:
        return self.terms.sum(-1)

    def means(self) -> dict[str, float]:
        out = {"reward": self.reward.mean().item()}
        out.update({name: self.terms[:, k].mean().item() for k, name in enumerate(TERMS)})
        out.update({f"r1 by {f:g} T": self.r1_by[:, k].mean().item() for k, f in enumerate(CHECKPOINTS)})
        out["charges onto unread cells"] = self.charged_first.mean().item()
        out["charges onto read cells"] = self.charged_read.mean().item()
        out["charges with an uncharged unread move"] = self.charged_avoidable.mean().item()
        out["rereads, first half"] = self.rereads[:, 0].mean().item()
        out["rereads, second half"] = self.rereads[:, 1].mean().item()
        out["stranded, first half"] = self.stranded[:, 0].mean().item()
        out["stranded, second half"] = self.stranded[:, 1].mean().item()
        out["m(U) given up stranded, first half"] = self.given_up[:, 0].mean().item()
        out["m(U) given up stranded, second half"] = self.given_up[:, 1].mean().item()
        return out


def _charges(config: EnvConfig, cells: torch.Tensor, zones: torch.Tensor) -> torch.Tensor:
    """``[...]`` how many zones r3 charges at each cell ``[..., 2]`` (zones ``[E, Z, 2]``, broadcast)."""
    shape = cells.shape[:-1]
    flat = cells.reshape(cells.shape[0], -1, 1, 2)
    squared = (flat - zones.unsqueeze(1)).pow(2).sum(-1).to(torch.float32)  # [E, M, Z]
    return config.violates(squared, config.no_fly_safety).sum(-1).view(shape)


@torch.no_grad()
def play(config: EnvConfig, policy_name: str, episodes: int, seed: int) -> Ledger:
    """One batch of ``episodes`` evaluation episodes of ``policy_name`` on ``config``, seeded with ``seed``."""
    config = policy_env(policy_name, config.replace(num_envs=episodes, expose_beliefs=False))
    env = MCRSEnv(config)
    policy = make_policy(policy_name, config, seed)
    obs_layout, state_layout = ObservationLayout.from_config(config), StateLayout.from_config(config)
    moves = torch.tensor(MOVES, dtype=torch.int64)
    E, T = episodes, config.max_steps
    terms = torch.zeros(E, len(TERMS), dtype=torch.float64)
    r1_by = torch.zeros(E, len(CHECKPOINTS), dtype=torch.float64)
    marks = {round(f * T): k for k, f in enumerate(CHECKPOINTS)}
    first = torch.zeros(E, dtype=torch.float64)
    read = torch.zeros(E, dtype=torch.float64)
    avoidable = torch.zeros(E, dtype=torch.float64)
    rereads = torch.zeros(E, 2, dtype=torch.float64)
    stranded = torch.zeros(E, 2, dtype=torch.float64)
    given_up = torch.zeros(E, 2, dtype=torch.float64)
    env.set_seed(seed)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.reset()
        zones = state_layout.cells(td.get("state"), state_layout.no_fly_position)  # [E, Z, 2]: static
        for t in range(T):
            td = policy(td)
            position = td.get(("agents", "position"))  # [E, N, 2]
            action, mask, half = td.get(ACTION), td.get(ACTION_MASK), int(t >= T // 2)
            every = position.unsqueeze(2) + moves  # [E, N, 8, 2]: each move's cell (off-grid ones masked)
            charged_every = _charges(config, every, zones)  # [E, N, 8]
            charged = charged_every.gather(2, action.unsqueeze(-1)).squeeze(-1)  # [E, N]
            dest = position + moves[action]
            flat = (dest[..., 0] * config.height + dest[..., 1]).clamp(0, config.n_cells - 1)
            unread = td.get("state_counts").sum(-1).gather(1, flat) == 0  # [E, N]: no UAV had read it
            if config.no_fly_prior == "known":  # a zone is known from reset: entering it buys no reading
                unread &= ~(dest.unsqueeze(2) == zones.unsqueeze(1)).all(-1).any(-1)
            own_unknown = obs_layout.unknown_by_action(td.get(OBSERVATION))  # [E, N, 8]: own m(U) there
            own_unread = own_unknown >= UNREAD
            safe_unread = (mask & (charged_every == 0) & own_unread).any(-1)
            chosen = own_unknown.gather(-1, action.unsqueeze(-1)).squeeze(-1)  # [E, N]: own m(U) of the move
            chosen_read = chosen < UNREAD
            unread_allowed = (mask & own_unread).any(-1)
            rereads[:, half] += (chosen_read & unread_allowed).sum(1).to(torch.float64)
            stranded[:, half] += (~unread_allowed).sum(1).to(torch.float64)
            best = own_unknown.masked_fill(~mask, -1.0).amax(-1)
            given_up[:, half] += ((best - chosen) * ~unread_allowed).sum(1).to(torch.float64)
            charged = charged.to(torch.float64)
            first += (charged * unread).sum(1)
            read += (charged * ~unread).sum(1)
            avoidable += (charged * safe_unread).sum(1)
            td = env.step(td)["next"]
            terms += td.get("reward_terms").to(torch.float64)
            if t + 1 in marks:
                r1_by[:, marks[t + 1]] = terms[:, 0]
    return Ledger(terms, r1_by, first, read, avoidable, rereads, stranded, given_up)


def table(ledgers: dict[str, Ledger]) -> str:
    """Markdown: one row per policy, the means over episodes of :meth:`Ledger.means`."""
    rows = {name: ledger.means() for name, ledger in ledgers.items()}
    columns = list(next(iter(rows.values())))
    body = [[name, *(f"{means[c]:.2f}" for c in columns)] for name, means in rows.items()]
    return markdown(["policy", *columns], body)


def policy_labels(names: list[str]) -> list[str]:
    """A row label per ``--policy``: a heuristic's name, or the last part of a checkpoint's path, with as many
    parent folders as it takes to tell it from the others (``model_000800000.pt`` of two runs:
    ``<run>/checkpoints/model_000800000.pt``)."""
    parts = [(name,) if name in POLICIES else Path(name).parts for name in names]
    depth = [1] * len(names)

    def label(k: int) -> str:
        return "/".join(parts[k][-depth[k] :])

    while True:
        labels = [label(k) for k in range(len(names))]
        clashing = [k for k in range(len(names)) if labels.count(labels[k]) > 1 and depth[k] < len(parts[k])]
        if not clashing:
            return labels
        for k in clashing:
            depth[k] += 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m mcrs_lab.analysis.ledger", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("--env", default="map20", choices=PRESETS, help="the scenario preset")
    parser.add_argument(
        "--policy",
        action="append",
        metavar="POLICY",
        help=f"a heuristic ({', '.join(POLICIES)}) or an mcrs-train run directory or .pt file; repeatable "
        "(default: every heuristic)",
    )
    parser.add_argument("--episodes", type=int, default=32, help="evaluation episodes, one batch")
    parser.add_argument("--seed", type=int, default=0, help="the evaluation seed (mcrs-eval's)")
    parser.add_argument("--shield", action="store_true", help="play with env.no_fly_shield=true")
    parser.add_argument("--uav-shield", action="store_true", help="play with env.uav_shield=true")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="an env field, e.g. discovery_rule=target (repeatable; a trained policy keeps the observation "
        "fields it was trained with)",
    )
    args = parser.parse_args(argv)
    if not 1 <= args.episodes <= 4096:
        raise SystemExit(f"ledger: error: --episodes={args.episodes}: must be in [1, 4096]")
    if not 0 <= args.seed < 2**63:
        raise SystemExit(f"ledger: error: --seed={args.seed}: must be in [0, 2**63 - 1]")
    config = scenario_with(
        "ledger", args.env, args.set, no_fly_shield=args.shield, uav_shield=args.uav_shield
    )
    ledgers = {}
    names = args.policy or list(POLICIES)
    for name, label in zip(names, policy_labels(names), strict=True):
        try:
            ledgers[label] = play(config, name, args.episodes, args.seed)
        except (CheckpointError, ValueError, OSError) as error:
            raise SystemExit(f"ledger: error: --policy={name}: {error}") from None
    print(
        f"{args.env}, safety_rule={config.safety_rule}, discovery_rule={config.discovery_rule}, "
        f"no_fly_view={config.no_fly_view}, no_fly_prior={config.no_fly_prior}, "
        f"no_fly_shield={str(args.shield).lower()}, "
        f"uav_shield={str(args.uav_shield).lower()}: means over {args.episodes} episodes (seed {args.seed}), "
        f"T = {config.max_steps}"
    )
    print(table(ledgers))
    return 0


if __name__ == "__main__":
    sys.exit(main())
