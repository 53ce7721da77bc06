"""``mcrs-train`` (also ``python -m mcrs.train``): train a learner (QMIX, VDN, QPLEX, EMC, EMU, SEMU,
CNN-SEMU).

    mcrs-train algo=qmix env=map20 seed=3
    mcrs-train -m algo=qmix,vdn,qplex seed=0,1,2
    mcrs-train resume=outputs/map10/qmix/<run>

A run directory under ``outputs/`` holds ``config.yaml``, ``train.log``, ``logs/`` (metrics),
``checkpoints/last.pt`` (everything needed to resume) and ``model_<steps>.pt`` (weights for ``mcrs-eval``).
A resumed session appends to the run's own directory. See docs/TRAINING.md.

The command checks its config before it loads torch, so the training stack is imported inside functions."""

from __future__ import annotations

import os
import signal
import sys
import threading


def _interrupted_while_loading(signum: int, frame: object) -> None:
    """Answer Ctrl-C while the command's modules load with one line instead of an import traceback."""
    print(f"mcrs-train: {signal.Signals(signum).name}: interrupted before training started: nothing to save",
          flush=True)  # fmt: skip
    raise SystemExit(128 + signum)


#: Installed only when this module runs as the command, never when a program imports it. After the imports
#: Ctrl-C is a KeyboardInterrupt again, which :func:`main` turns into the same line.
_LOADING = (
    (__name__ == "__main__" or os.path.basename(sys.argv[0] if sys.argv else "") == "mcrs-train")
    and threading.current_thread() is threading.main_thread()
    and signal.getsignal(signal.SIGINT) is signal.default_int_handler
)
if _LOADING:
    signal.signal(signal.SIGINT, _interrupted_while_loading)

import logging
import shutil
import warnings
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from mcrs.experiment.commands.cli import one_line_errors, remove_refused_dirs
from mcrs.experiment.config import (
    CONFIG_DIR,
    RESUME_MUTABLE,
    Config,
    ConfigError,
    as_typed,
    register_configs,
    validation_errors,
)
from mcrs.experiment.run.history import current_config, legacy_values
from mcrs.experiment.run.interrupt import RunInterrupted, TerminateAsInterrupt
from mcrs.experiment.run.rundir import RunDirError, describe_os_error, register_resolvers, resume_problem
from mcrs.experiment.schema import ENTRY_POINT_GROUP
from mcrs.experiment.training.whole_batches import whole_batch_errors
from mcrs.experiment.util.untrusted import UntrustedInput, read_yaml


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
    """Return the config of the run in ``cfg.resume`` with this command's mutable fields applied. It refuses a
    directory that is not a run, and explicit overrides that contradict the run."""
    run_dir = Path(str(cfg.resume)).expanduser()
    saved_path = run_dir / "config.yaml"
    problem = resume_problem(cfg.resume)
    if problem:
        raise ConfigError(problem)
    raw = _read_run_config(saved_path)
    saved = current_config(raw)
    legacy = legacy_values(raw)
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
        # a key the command sets, inside it (env set, env.width differs) or under it (algo.options.bonus
        # set, algo.options missing from the saved run)
        overridden = any(name == e or name.startswith(e + ".") or e.startswith(name + ".") for e in explicit)
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
    """Read a run's ``config.yaml`` with bounded size and depth and OmegaConf's safe loader. Anything
    unreadable, a ``!!python`` tag included, becomes one :class:`ConfigError` line naming the file."""
    try:
        saved = read_yaml(path, interpolations=False)
    except UntrustedInput as error:
        raise ConfigError(f"resume: {error}") from None
    if not isinstance(saved, dict):
        raise ConfigError(f"resume: {path} is not a valid config: expected a mapping of fields")
    return saved


def run(cfg: DictConfig, run_dir: Path, overrides: list[str] | None = None) -> dict[str, float]:
    """Train as configured (or resume ``cfg.resume``) and print where the results are."""
    from mcrs.experiment.training.algorithms import UnregisteredAlgorithm
    from mcrs.experiment.training.trainer import Experiment

    resume = cfg.resume is not None
    if resume:
        cfg, run_dir = resume_config(cfg, overrides or [])
    with warnings.catch_warnings():  # said below as a note: line
        warnings.simplefilter("ignore", UnregisteredAlgorithm)
        experiment = Experiment(cfg, run_dir, resume=resume)
    print(
        f"{'resuming' if resume else 'training'} {cfg.algo.name} on {experiment.task.name}: {run_dir}",
        flush=True,
    )
    if experiment.algorithm_note:  # a label of one's own, or a misspelt name: said, not refused
        print(f"note: {experiment.algorithm_note}")
    done = experiment.counters.env_steps
    if resume and experiment.finished:
        print(
            f"note: the run is already at {done:,} env steps (train.total_env_steps={cfg.train.total_env_steps:,}): "
            "nothing to train; pass a larger train.total_env_steps to train on",
            flush=True,
        )
    elif resume and done >= cfg.train.total_env_steps:
        print(
            f"note: the run reached {done:,} env steps but stopped before its final evaluation: "
            "evaluating and saving it now",
            flush=True,
        )
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
    """Write the ``report=true`` report into ``run_dir/report`` (:func:`mcrs.evaluate.evaluate_run`) and say
    where it is."""
    from mcrs.evaluate import evaluate_run

    steps = experiment.counters.env_steps
    label = f"{cfg.algo.name} ({f'{steps / 1000:g}k' if steps >= 1000 else steps} steps)"
    episodes, seed = int(cfg.train.eval_episodes), int(cfg.train.eval_seed)
    if experiment.config.task is not None:  # another task: the random baseline, its learning curve
        from mcrs.evaluate import evaluate_task_report

        table, curve, rewards = evaluate_task_report(run_dir, label, episodes, seed, str(cfg.device))
        listed = ", ".join(f"{name} {mean:.1f}" for name, (mean, _) in rewards.items())
        print(
            f"report ({experiment.task.name}, episode reward: {listed}):\n"
            f"  metric table    {table}\n  learning curve  {curve}",
            flush=True,
        )
        return
    print(f"evaluating {label} and the heuristics on {episodes} episodes ...", flush=True)
    report = evaluate_run(run_dir, experiment.env_config, label, episodes, seed, cfg.logger.progress_bar)
    rewards = ", ".join(f"{name} {mean:.1f}" for name, (mean, _) in report.rewards.items())
    print(
        f"report ({cfg.env.name}, episode reward: {rewards}):\n"
        f"  metric table    {report.table}\n"
        f"  learning curve  {report.curve}\n"
        f"  episode GIF     {report.gif}",
        flush=True,
    )
    if cfg.get("budget") == "quickstart":
        print(
            f"quickstart: a smoke test of the pipeline ({steps:,} env steps), not a result: budget=campaign "
            "(1M env steps, docs/RESULTS.md) or budget=paper (the paper's 2M) trains a policy to compare",
            flush=True,
        )


def early_errors(cfg: DictConfig, overrides: list[str]) -> list[str]:
    """Return what is wrong with a fresh run's config that can be told without torch.

    These are the values (:func:`validation_errors` without the device, resource and embedding checks that
    :class:`Experiment` makes) and lengths or intervals that whole collector batches cannot honour. A
    resume is judged against its run's config later (:func:`resume_config`)."""
    if cfg.resume is not None:
        return []
    try:
        problems = validation_errors(cfg, deep=False)
    except ConfigError as error:
        return [str(error).removeprefix("invalid config: ")]
    explicit = {o.split("=", 1)[0].lstrip("+~") for o in overrides}
    return problems + env_name_errors(cfg) + whole_batch_errors(cfg, explicit) + option_errors(cfg)


#: What makes a map a preset: a run named after a preset must have these values of it.
PRESET_FIELDS = ("width", "height", "n_uavs", "n_targets", "n_no_fly")


def env_name_errors(cfg: DictConfig) -> list[str]:
    """Check ``env.name``, which names the run's directory and the map its records are filed under. It must be
    a plain name, not an interpolation, and not a preset's name (conf/env/) on another map."""
    if OmegaConf.is_interpolation(cfg.env, "name"):
        raw = OmegaConf.to_container(cfg.env, resolve=False)["name"]
        return [f"env.name={raw}: must be a plain name, not an interpolation: it names the run's directory "
                "and the map its records are filed under"]  # fmt: skip
    name = str(cfg.env.name)
    preset = Path(CONFIG_DIR, "env", f"{name}.yaml")
    if not preset.is_file():
        return []
    values = OmegaConf.load(preset)
    differ = [f"{f}={cfg.env.get(f)!r} (the preset's {values.get(f)!r})" for f in PRESET_FIELDS
              if f in values and cfg.env.get(f) != values.get(f)]  # fmt: skip
    if not differ:
        return []
    return [f"env.name={name!r} names the preset env={name}, but this run has {', '.join(differ)}: a run may "
            f"not pass for a map it is not; choose env={name}, or another name"]  # fmt: skip


def option_errors(cfg: DictConfig) -> list[str]:
    """Return what the run's algorithm says of ``algo.options`` when any are given or the algorithm is
    installed. A sweep is thus checked before its first job. Only then is the algorithm's module, and
    torch, loaded."""
    installed = entry_points(group=ENTRY_POINT_GROUP, name=str(cfg.algo.name))
    if not cfg.algo.get("options") and not installed:
        return []
    from mcrs.experiment.training.algorithms import algorithm_class

    algo = as_typed(cfg).algo
    try:
        algorithm_class(algo).read_options(algo)
    except ConfigError as error:
        return [str(error)]
    return []


def _remove_session_files(run_dir: Path, output_subdir: str | None) -> None:
    """Remove a refused resume's Hydra files (``.hydra/resumed_*``), leaving the run as it was."""
    if output_subdir and Path(output_subdir).name.startswith("resumed_"):
        shutil.rmtree(run_dir / output_subdir, ignore_errors=True)


register_configs()
register_resolvers()
if _LOADING and signal.getsignal(signal.SIGINT) is _interrupted_while_loading:
    signal.signal(signal.SIGINT, signal.default_int_handler)


@one_line_errors("mcrs-train", interrupted="interrupted before training started: nothing to save")
@hydra.main(config_path=CONFIG_DIR, config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> float:
    """Console entry point; returns the final evaluation reward (for Hydra sweepers)."""
    hydra_cfg = HydraConfig.get()
    run_dir = Path(hydra_cfg.runtime.output_dir)
    overrides = list(hydra_cfg.overrides.task)
    problems = early_errors(cfg, overrides)
    if problems:  # refused before torch, TorchRL and the learners load: at once, and nothing is left behind
        logging.getLogger(__name__).error("invalid config: %s", "; ".join(problems), extra={"console": False})
        remove_refused_dirs(run_dir)
        listed = problems[0] if len(problems) == 1 else "\n  - " + "\n  - ".join(problems)
        raise SystemExit(f"mcrs-train: error: invalid config: {listed}")

    from mcrs.experiment.run import checkpoint as ckpt
    from mcrs.experiment.training.collection import CollectorWorkerFailed
    from mcrs.objectives.gradient import TrainingDiverged

    try:
        with TerminateAsInterrupt():
            result = run(cfg, run_dir, overrides)
    except RunInterrupted as stop:  # Ctrl-C or SIGTERM: the checkpoint is written; one line, no traceback
        logging.getLogger("mcrs.run").info(  # train.log: where this session ended (a resume appends)
            "%s: stopped at env step %d, checkpoint %s", stop.signal_name, stop.env_steps, stop.checkpoint
        )
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
            _remove_session_files(run_dir, hydra_cfg.output_subdir)
        # one clear message (with the cause), no traceback
        raise SystemExit(f"mcrs-train: error: {error}") from None
    except OSError as error:  # an I/O failure outside the checkpoint writes (which say what is intact)
        raise SystemExit(f"mcrs-train: error: {describe_os_error(error)}") from None
    return float(result.get("episode_reward", float("nan")))


if __name__ == "__main__":
    main()
