"""``mcrs-train`` (also ``python -m mcrs.train``): train QMIX, VDN or QPLEX on MCRS-LCR.

    mcrs-train algo=qmix env=map20 seed=3
    mcrs-train -m algo=qmix,vdn,qplex seed=0,1,2
    mcrs-train resume=outputs/map10/qmix/2026-11-21_10-00-00_seed0

Each run writes under ``outputs/`` (``hydra.run.dir``): ``config.yaml`` (the resolved config),
``logs/`` (metrics), ``checkpoints/last.pt`` (everything needed to resume) and ``model_<steps>.pt``
(weights, for ``mcrs-eval checkpoint=...``). See docs/TRAINING.md.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from mcrs.experiment import checkpoint as ckpt
from mcrs.experiment.cli import one_line_errors, remove_refused_dirs
from mcrs.experiment.config import (
    CONFIG_DIR,
    RESUME_MUTABLE,
    Config,
    ConfigError,
    register_configs,
)
from mcrs.experiment.rundir import RunDirError, describe_os_error, register_resolvers
from mcrs.experiment.untrusted import UntrustedInput, read_yaml


def _is_mutable(name: str) -> bool:
    return any(name == m or name.startswith(m + ".") for m in RESUME_MUTABLE)


def _differences(saved: Any, current: Any, prefix: str = "") -> list[str]:
    if isinstance(saved, dict) and isinstance(current, dict):
        out: list[str] = []
        for key in sorted(set(saved) | set(current)):
            out += _differences(saved.get(key, "<missing>"), current.get(key, "<missing>"), f"{prefix}{key}.")
        return out
    name = prefix[:-1]
    return [] if saved == current else [f"{name}: the run has {saved!r}, this command has {current!r}"]


def resume_config(cfg: DictConfig, overrides: list[str]) -> tuple[DictConfig, Path]:
    """The config of the run in ``cfg.resume`` with the mutable fields of this command applied.

    Refuses a directory that is not a run, and a command whose explicit overrides contradict the run.
    """
    run_dir = Path(str(cfg.resume)).expanduser()
    saved_path = run_dir / "config.yaml"
    if not run_dir.is_dir():
        raise ConfigError(f"resume={cfg.resume}: no such directory")
    if not saved_path.is_file() or not ckpt.checkpoint_path(run_dir).is_file():
        raise ConfigError(
            f"resume={cfg.resume}: not an mcrs-train run directory (needs config.yaml and checkpoints/{ckpt.LAST})"
        )
    raw = _read_run_config(saved_path)
    saved = ckpt.current_config(raw)
    legacy = ckpt.legacy_values(raw)
    if legacy:  # nothing saved is reinterpreted: the run goes on under the rules it was trained with
        print(
            f"mcrs-train: {saved_path} was written before {', '.join(v.split('=')[0] for v in legacy)} "
            f"existed: resuming it as it was trained ({', '.join(legacy)})",
            flush=True,
        )
    current = OmegaConf.to_container(cfg, resolve=True, enum_to_str=True)
    explicit = {o.split("=", 1)[0].lstrip("+~") for o in overrides}
    conflicts = []
    for line in _differences(saved, current):
        name = line.split(":", 1)[0]
        overridden = any(name == e or name.startswith(e + ".") for e in explicit)
        if overridden and not _is_mutable(name):
            conflicts.append(line)
    if conflicts:
        raise ConfigError(
            f"resume={cfg.resume}: the command contradicts the run's config:\n  - " + "\n  - ".join(conflicts)
        )
    try:
        merged = OmegaConf.merge(OmegaConf.structured(Config), saved)
    except OmegaConfBaseException as error:  # an unknown key or a wrong type in the run's config.yaml
        raise ConfigError(
            f"resume: {saved_path} does not fit this mcrs's config: {_first_line(error)}"
        ) from None
    for key in explicit:  # exactly what the command line set, e.g. logger.progress_bar, not all of logger
        if _is_mutable(key) and key != "resume":
            OmegaConf.update(merged, key, OmegaConf.select(cfg, key), merge=False)
    merged.resume = str(run_dir)
    return merged, run_dir


def _first_line(error: BaseException) -> str:
    return (str(error).strip().splitlines() or [type(error).__name__])[0]


def _read_run_config(path: Path) -> dict[str, Any]:
    """A run's ``config.yaml``, bounded before it is parsed (size, depth, no aliases or interpolations:
    mcrs.experiment.untrusted) and through OmegaConf's safe loader (a ``!!python`` tag is refused, never
    run); anything unreadable is one :class:`ConfigError` line naming the file."""
    try:
        saved = read_yaml(path, interpolations=False)
    except UntrustedInput as error:
        raise ConfigError(f"resume: {error}") from None
    if not isinstance(saved, dict):
        raise ConfigError(f"resume: {path} is not a valid config: expected a mapping of fields")
    return saved


def run(cfg: DictConfig, run_dir: Path, overrides: list[str] | None = None) -> dict[str, float]:
    """Train as configured (or resume ``cfg.resume``) and print where the results are."""
    from mcrs.experiment.trainer import Experiment

    resume = cfg.resume is not None
    if resume:
        cfg, run_dir = resume_config(cfg, overrides or [])
    experiment = Experiment(cfg, run_dir, resume=resume)
    print(f"{'resuming' if resume else 'training'} {cfg.algo.name} on {cfg.env.name}: {run_dir}", flush=True)
    result = experiment.run()
    reward = result.get("episode_reward", float("nan"))
    print(
        f"final greedy evaluation ({cfg.train.eval_episodes} episodes): episode reward {reward:.2f}",
        flush=True,
    )
    print(f"run directory: {run_dir}", flush=True)
    if cfg.report:
        try:
            write_report(experiment, cfg, run_dir)
        except KeyboardInterrupt as stop:  # Ctrl-C or SIGTERM; the run itself is complete and saved
            print(f"mcrs-train: report interrupted; the trained run is complete in {run_dir}", flush=True)
            raise SystemExit(getattr(stop, "exit_code", 130)) from None
    return result


def write_report(experiment: Any, cfg: DictConfig, run_dir: Path) -> None:
    """``report=true``: the trained policy and the heuristics on the evaluation episodes, the learning
    curve and a GIF into ``run_dir/report`` (:func:`mcrs.evaluate.evaluate_run`), and where they are."""
    from mcrs.evaluate import evaluate_run

    steps = experiment.counters.env_steps
    label = f"{cfg.algo.name} ({f'{steps / 1000:g}k' if steps >= 1000 else steps} steps)"
    episodes, seed = int(cfg.train.eval_episodes), int(cfg.train.eval_seed)
    print(f"evaluating {label} and the heuristics on {episodes} episodes ...", flush=True)
    report = evaluate_run(run_dir, experiment.env_config, label, episodes, seed)
    rewards = ", ".join(f"{name} {mean:.1f}" for name, (mean, _) in report.rewards.items())
    print(
        f"report ({cfg.env.name}, episode reward: {rewards}):\n"
        f"  metric table    {report.table}\n"
        f"  learning curve  {report.curve}\n"
        f"  episode GIF     {report.gif}",
        flush=True,
    )


register_configs()
register_resolvers()


@one_line_errors("mcrs-train")
@hydra.main(config_path=CONFIG_DIR, config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> float:
    """Console entry point; returns the final evaluation reward (for Hydra sweepers)."""
    from hydra.core.hydra_config import HydraConfig

    from mcrs.experiment.collection import CollectorWorkerFailed
    from mcrs.experiment.interrupt import RunInterrupted, TerminateAsInterrupt
    from mcrs.objectives.gradient import TrainingDiverged

    hydra_cfg = HydraConfig.get()
    run_dir = Path(hydra_cfg.runtime.output_dir)
    try:
        with TerminateAsInterrupt():
            result = run(cfg, run_dir, list(hydra_cfg.overrides.task))
    except RunInterrupted as stop:  # Ctrl-C or SIGTERM: the checkpoint is written; one line, no traceback
        print(
            f"mcrs-train: {stop.signal_name}: stopped at env step {stop.env_steps}, checkpoint {stop.checkpoint}\n"
            f"resume with: mcrs-train resume={stop.run_dir}",
            flush=True,
        )
        raise SystemExit(stop.exit_code) from None
    except KeyboardInterrupt as stop:  # Ctrl-C or SIGTERM before training started: nothing to save
        remove_refused_dirs(run_dir)
        name = getattr(stop, "signal_name", "SIGINT")
        print(f"mcrs-train: {name}: interrupted before training started: nothing to save", flush=True)
        raise SystemExit(getattr(stop, "exit_code", 130)) from None
    except (ConfigError, ckpt.CheckpointError, TrainingDiverged, CollectorWorkerFailed, RunDirError) as error:
        logging.getLogger(__name__).error("%s", error, extra={"console": False})  # train.log; printed below
        if cfg.resume is not None or isinstance(error, ConfigError):
            remove_refused_dirs(run_dir)  # the directories Hydra made for a run that never started
        # one clear message (with the cause), no traceback
        raise SystemExit(f"mcrs-train: error: {error}") from None
    except OSError as error:  # an I/O failure outside the checkpoint writes (which say what is intact)
        raise SystemExit(f"mcrs-train: error: {describe_os_error(error)}") from None
    return float(result.get("episode_reward", float("nan")))


if __name__ == "__main__":
    main()
