"""``mcrs-render``: draw one episode of a policy as a scene, the figure-4 contours and an animation.

It takes the same ``key=value`` overrides as ``mcrs-train`` and ``mcrs-eval`` (``conf/render.yaml``); the
pictures go into ``out``, one numbered folder per job of a ``-m`` sweep::

    mcrs-render env=map20 policy=lawnmower seed=3 out=outputs/render gif=false
    mcrs-render env.comm_range=3 uav=2
    mcrs-render policy=outputs/map10/qmix/<run>        (a trained agent's episode)

Torch and matplotlib are imported inside functions, so a bad config is refused at once."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra
from hydra.core.config_store import ConfigStore
from hydra.core.hydra_config import HydraConfig
from omegaconf import MISSING, DictConfig

from mcrs.env.config import EnvConfig, from_mapping
from mcrs.experiment.commands.cli import one_line_errors, remove_refused_dirs
from mcrs.experiment.run.rundir import register_resolvers
from mcrs.experiment.schema import CONFIG_DIR, MAX_SEED

SCHEMA_NAME = "mcrs_render"


@dataclass
class RenderConfig:
    """The typed fields of ``conf/render.yaml``, so Hydra refuses ``seed=abc`` or ``gif=maybe`` itself."""

    env: Any = MISSING  # the env group (conf/env/), validated by mcrs.env.config.from_mapping
    policy: str = "greedy"  # random | lawnmower | greedy | coverage | a checkpoint (.pt, run dir) or .pt2
    seed: int = 0  # the episode's and the policy's seed
    uav: int = 0  # the UAV of the uncertainty contours
    gif: bool = True  # also write episode.gif
    out: str = "outputs/render"  # the folder of the pictures (hydra.run.dir; conf/render.yaml: unique)


def register_configs() -> None:
    """Register the schema (``conf/render.yaml`` names ``mcrs_render`` in its defaults)."""
    ConfigStore.instance().store(name=SCHEMA_NAME, node=RenderConfig)


def checked(cfg: DictConfig) -> tuple[EnvConfig, str]:
    """Return the env config and the policy of ``cfg``, every value checked before drawing starts."""
    from mcrs.policies import POLICIES, make_policy, policy_env

    try:
        env_config = from_mapping(cfg.env)
    except TypeError as error:
        raise ValueError(str(error)) from None
    policy = str(cfg.policy)
    if policy not in POLICIES:
        make_policy(policy, policy_env(policy, env_config))  # a checkpoint: fails early, naming the problem
    if not 0 <= cfg.seed <= MAX_SEED:
        raise ValueError(f"seed={cfg.seed}: must be in [0, 2**63 - 1]")
    if not 0 <= cfg.uav < env_config.n_uavs:
        raise ValueError(
            f"uav={cfg.uav}: must be in 0..{env_config.n_uavs - 1} ({env_config.name} has {env_config.n_uavs} UAVs)"
        )
    return env_config, policy


def run(cfg: DictConfig, out_dir: Path) -> list[Path]:
    """Check ``cfg``, draw its episode into ``out_dir`` and print the paths written."""
    from mcrs.viz import write_episode_pictures

    env_config, policy = checked(cfg)
    paths = write_episode_pictures(
        out_dir, env_config, policy, int(cfg.seed), gif=bool(cfg.gif), uav=int(cfg.uav)
    )
    for path in paths:
        print(path, flush=True)
    return paths


register_configs()
register_resolvers()  # ${mcrs.pid:} and ${mcrs.beside_run:...} in conf/render.yaml's out


@one_line_errors("mcrs-render")
@hydra.main(config_path=CONFIG_DIR, config_name="render", version_base=None)
def main(cfg: DictConfig) -> None:
    """Console entry point ``mcrs-render`` (Hydra ``key=value`` overrides, ``--help``, ``-m`` sweeps)."""
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        run(cfg, out_dir)
    except ValueError as error:  # bad input: one clear message, no traceback
        remove_refused_dirs(out_dir)  # Hydra made it for this run: leave no empty folder behind
        raise SystemExit(f"mcrs-render: error: {error}") from None


if __name__ == "__main__":
    main()
