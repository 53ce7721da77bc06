"""How evaluation tables name a policy or a run, and the episodes a trained policy is evaluated on by default."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mcrs.policies import POLICIES

#: Episodes and seed of an evaluation of heuristics only, when the command names neither.
HEURISTIC_EPISODES, HEURISTIC_SEED = 32, 0


def default_episodes_seed(names: list[str]) -> tuple[int, int]:
    """The episodes and seed an evaluation of ``names`` runs when the command names neither: the first
    trained policy's training evaluations (``train.eval_episodes``, ``train.eval_seed``), so its figures are
    those its run logged; an exported agent's are the training defaults (its file keeps no train config);
    heuristics alone: 32 episodes of seed 0."""
    from mcrs.experiment.run import checkpoint as ckpt
    from mcrs.experiment.schema import TrainConfig
    from mcrs.policies.trained import is_exported, looks_like_checkpoint, resolve_checkpoint

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
    """A policy as tables name it: a heuristic by its name, a trained run by its run name (its folder),
    with its algorithm when the name does not hold it (``<date>_<time>_<pid>_seed0 (qmix)``), a
    checkpoint file of a run as ``<run>/<file stem>`` and an exported agent by its file name."""
    from mcrs.policies.trained import is_exported, looks_like_checkpoint

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
    """The algorithm a run directory's ``config.yaml`` names (None when it cannot be read)."""
    from mcrs.experiment.util.untrusted import UntrustedInput, read_yaml

    try:
        algo = (read_yaml(run_dir / "config.yaml", interpolations=False) or {}).get("algo") or {}
    except (OSError, UntrustedInput, ValueError):
        return None
    name = algo.get("name") if isinstance(algo, dict) else None
    return name if isinstance(name, str) else None


def run_task_name(run_dir: Path) -> str:
    """The task's name in a task run's ``config.yaml`` (its class name when the node has no ``name``)."""
    from mcrs.experiment.run.rundir import task_name
    from mcrs.experiment.util.untrusted import read_yaml

    node = read_yaml(run_dir / "config.yaml", interpolations=False).get("task") or {}
    return task_name(node, "task")
