"""``mcrs-render``: draw one episode of a policy (scene, figure-4 contours, animation) without Hydra.

mcrs-render --env map20 --policy lawnmower --seed 3 --out outputs/render --no-gif
mcrs-render --env map10 --set comm_range=3 --uav 2
mcrs-render --env map10 --policy outputs/map10/qmix/<run>      (a trained agent's episode)
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from omegaconf import OmegaConf

from mcrs.env.config import SCENARIOS, EnvConfig, scenario
from mcrs.policies import POLICIES


def parse_overrides(items: Sequence[str]) -> dict:
    """``["comm_range=3", "max_steps=20"]`` -> typed values (YAML parsing, as Hydra would)."""
    overrides = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise argparse.ArgumentTypeError(f"--set expects KEY=VALUE, got {item!r}")
        overrides[key] = OmegaConf.create(f"v: {value}").v
    return overrides


def render(
    env_config: EnvConfig, policy: str, seed: int, out: Path, gif: bool = True, uav: int = 0
) -> list[Path]:
    """Write scene.png, uncertainty_contours.png and (optionally) episode.gif for one episode."""
    from mcrs.env.render import plot_scene, plot_uncertainty_contours, rollout_episode, save_episode_gif

    out.mkdir(parents=True, exist_ok=True)
    episode = rollout_episode(env_config, policy, seed)
    without = rollout_episode(env_config.replace(comm_range=0.0), policy, seed)
    paths = [out / "scene.png", out / "uncertainty_contours.png"]
    plot_scene(episode, env_config, paths[0])
    plot_uncertainty_contours(episode, without, env_config, paths[1], uav=uav)
    if gif:
        paths.append(save_episode_gif(episode, env_config, out / "episode.gif"))
    return paths


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mcrs-render", description=__doc__.split("\n")[0])
    parser.add_argument("--env", default="map10", choices=SCENARIOS, help="map preset (default map10)")
    parser.add_argument(
        "--policy",
        default="greedy",
        help=f"{', '.join(sorted(POLICIES))} (default greedy), or an mcrs-train checkpoint / run directory",
    )
    parser.add_argument("--seed", type=int, default=0, help="episode and policy seed (default 0)")
    parser.add_argument("--out", type=Path, default=Path("outputs/render"), help="output folder")
    parser.add_argument(
        "--gif", action=argparse.BooleanOptionalAction, default=True, help="write episode.gif"
    )
    parser.add_argument("--uav", type=int, default=0, help="UAV of the uncertainty contours (default 0)")
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="environment field override, repeatable, e.g. --set comm_range=3",
    )
    return parser


def main(argv: Sequence[str] | None = None) -> None:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        env_config = scenario(args.env, **parse_overrides(args.overrides))
        if args.policy not in POLICIES:
            from mcrs.policies import make_policy

            make_policy(args.policy, env_config)  # fails early, naming the problem
        if not 0 <= args.uav < env_config.n_uavs:
            raise ValueError(f"--uav {args.uav}: must be in 0..{env_config.n_uavs - 1}")
    except (ValueError, argparse.ArgumentTypeError) as error:
        parser.error(str(error))
    for path in render(env_config, args.policy, args.seed, args.out, gif=args.gif, uav=args.uav):
        print(path)


if __name__ == "__main__":
    main()
