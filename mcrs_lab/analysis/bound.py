"""An upper bound on the episode reward of any policy, per penalty rule: how much reward a map admits.

The team takes ``N * T`` readings an episode, one per UAV and step. Give every reading to the cell where
it gains most, as if the UAVs could jump anywhere and the sensor read in their favour: the k-th reading of
a cell earns w1 times the drop of that cell's m(U), plus w2 when its m(F) first reaches tau, less w3 for
every zone that r3 charges at that cell under ``safety_rule``. In their favour means a run of F readings
on a target cell, and on any other cell a run of E readings, or of F readings where r2 pays any cell
reaching tau (``discovery_rule=belief``) and the sensor can read F there (``p_false_alarm > 0``). A run of
one kind is the best a cell can do: r1 over k readings is 1 - m(U) after them, which conflicting readings
only raise, and a discovery needs F readings. A known no-fly cell (``no_fly_prior=known``) gains nothing.
No paths, no collisions, no sensing at reset: every one of these only lowers what a real policy gets, so
the sum of the ``N * T`` best gains bounds the reward of every policy on that layout. Under eq. 24 with a
sensor that errs that bound counts every cell as a discovery, so the tool also prints the bound with a
sensor that never errs: what the map admits when no discovery is false. The layouts are the env's own,
drawn with the evaluation seed.

    python -m mcrs_lab.analysis.bound --env map20 [--episodes 32] [--seed 0] [--set p_false_alarm=0.1 ...]
"""

from __future__ import annotations

import argparse
import sys

import torch

from mcrs.env.belief import belief_masses
from mcrs.env.config import PRESETS, SAFETY_RULES, EnvConfig
from mcrs.env.core import MCRSCore
from mcrs_lab.analysis.env_fields import scenario_with

#: Readings of one cell considered: beyond about ten, (1 - m)^k adds nothing visible.
MAX_READINGS = 12


def reading_gains(config: EnvConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """``[K]`` gains of a cell's 1st..K-th perfect reading: on an empty cell, and on a target cell."""
    k = torch.arange(MAX_READINGS + 1)
    zero = torch.zeros_like(k)
    _, _, unknown_empty = belief_masses(zero, k, config.m_f, config.m_e)
    _, full, unknown_target = belief_masses(k, zero, config.m_f, config.m_e)
    drop_empty = unknown_empty[:-1] - unknown_empty[1:]
    drop_target = unknown_target[:-1] - unknown_target[1:]
    reached = full >= config.target_threshold
    discovered = (reached[1:] & ~reached[:-1]).to(torch.float32)  # the reading that first reaches tau
    return (
        config.w_uncertainty * drop_empty,
        config.w_uncertainty * drop_target + config.w_discovery * discovered,
    )


def reward_bound(config: EnvConfig, episodes: int, seed: int) -> torch.Tensor:
    """``[episodes]``: the bound on each layout of ``episodes`` resets drawn with ``seed``."""
    core = MCRSCore(config.replace(num_envs=episodes, no_fly_shield=False))
    core.seed(seed)
    core.reset()
    cells = torch.arange(config.n_cells)
    xy = torch.stack([cells // config.height, cells % config.height], -1).to(torch.float32)  # [C, 2]
    squared = (
        (xy.view(1, -1, 1, 2) - core.no_fly_pos.to(torch.float32).unsqueeze(1)).pow(2).sum(-1)
    )  # [E, C, Z]
    penalty = config.w_no_fly * config.violates(squared, config.no_fly_safety).sum(-1)  # [E, C]
    empty, target = reading_gains(config)
    if config.discovery_rule == "belief" and config.p_false_alarm > 0:
        empty = target  # an empty cell read F until tau is paid as a discovery (eq. 24)
    gains = torch.where(core.is_target.unsqueeze(-1), target, empty)  # [E, C, K]
    if config.no_fly_prior == "known":
        gains = gains.masked_fill(core.is_no_fly.unsqueeze(-1), 0.0)
    gains = gains - penalty.unsqueeze(-1)
    budget = min(config.n_uavs * config.max_steps, gains[0].numel())
    return gains.flatten(1).topk(budget, dim=1).values.clamp(min=0.0).sum(1)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m mcrs_lab.analysis.bound", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("--env", default="map20", choices=PRESETS, help="the scenario preset")
    parser.add_argument("--episodes", type=int, default=32, help="layouts averaged over")
    parser.add_argument("--seed", type=int, default=0, help="the seed the layouts are drawn with")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="an env field, e.g. p_false_alarm=0.1 or discovery_rule=target (repeatable)",
    )
    args = parser.parse_args(argv)
    if args.episodes < 1:
        raise SystemExit(f"bound: error: --episodes={args.episodes}: must be >= 1")
    base = scenario_with("bound", args.env, args.set)
    shown = ("no_fly_prior", "discovery_rule", "p_detect", "p_false_alarm")
    setting = " ".join(f"{name}={getattr(base, name)}" for name in shown)
    for rule in SAFETY_RULES:
        config = base.replace(safety_rule=rule)
        bound = reward_bound(config, args.episodes, args.seed)
        perfect = reward_bound(config.replace(p_detect=1.0, p_false_alarm=0.0), args.episodes, args.seed)
        print(
            f"{args.env} safety_rule={rule} {setting}: reward bound {bound.mean():.1f} "
            f"(min {bound.min():.1f}, max {bound.max():.1f}); with a sensor that never errs "
            f"{perfect.mean():.1f}; {args.episodes} layouts, seed {args.seed}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
