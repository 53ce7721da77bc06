"""How evaluation tables name a policy or a run, and the episodes a trained policy is evaluated on by default."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.run.rundir import task_name
from mcrs.experiment.schema import TrainConfig
from mcrs.experiment.util.untrusted import UntrustedInput, read_yaml
from mcrs.policies import POLICIES
from mcrs.policies.trained import is_exported, looks_like_checkpoint, resolve_checkpoint

#: Episodes and seed of an evaluation of heuristics only, when the command names neither.
HEURISTIC_EPISODES, HEURISTIC_SEED = 32, 0


def default_episodes_seed(names: list[str]) -> tuple[int, int]:
    """Return the episodes and seed an evaluation of ``names`` runs when the command names neither.

    They are the first trained policy's training evaluation settings, so its figures match its run's log.
    An exported agent keeps no train config and gets the training defaults; heuristics alone get 32
    episodes of seed 0."""
    trained = [name for name in names if name not in POLICIES and looks_like_checkpoint(name)]
    if not trained:
        return HEURISTIC_EPISODES, HEURISTIC_SEED
    train: Any = {}
    if not is_exported(trained[0]):
        try:
            state = ckpt.load(resolve_checkpoint(trained[0]), mmap=True)
            train = state["config"]["train"]
        except (ckpt.CheckpointError, OSError, KeyError, TypeError):
            train = {}  # loading the policy names the problem
    defaults = TrainConfig()
    episodes = train.get("eval_episodes", defaults.eval_episodes) if isinstance(train, dict) else None
    seed = train.get("eval_seed", defaults.eval_seed) if isinstance(train, dict) else None
    return int(episodes or defaults.eval_episodes), int(seed if seed is not None else defaults.eval_seed)


def policy_label(name: str) -> str:
    """Return a policy's name in tables. A heuristic is named by its name, a run by its folder (with its
    algorithm when the name lacks it), a checkpoint file as ``<run>/<file stem>`` and an exported agent by
    its file name."""
    if name in POLICIES or not looks_like_checkpoint(name):
        return name
    path = Path(name).expanduser()
    if is_exported(name):
        return path.name
    if path.suffix == ".pt":
        run = path.parent.parent if path.parent.name == "checkpoints" else path.parent
        return f"{run.name}/{path.stem}"
    algo = _algo_of(path)
    return f"{path.name} ({algo})" if algo and algo not in path.name else path.name


def _algo_of(run_dir: Path) -> str | None:
    """Return the algorithm a run directory's ``config.yaml`` names, or None."""
    try:
        algo = (read_yaml(run_dir / "config.yaml", interpolations=False) or {}).get("algo") or {}
    except (OSError, UntrustedInput, ValueError):
        return None
    name = algo.get("name") if isinstance(algo, dict) else None
    return name if isinstance(name, str) else None


def run_task_name(run_dir: Path) -> str:
    """Return the task's name in a task run's ``config.yaml``, or its class name."""
    node = read_yaml(run_dir / "config.yaml", interpolations=False).get("task") or {}
    return task_name(node, "task")
