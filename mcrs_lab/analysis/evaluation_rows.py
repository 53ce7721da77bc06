"""One policy's results in one ``mcrs-eval`` run, as the report reads them (a row of ``metrics.csv`` or of an
evaluation record), and where the scenario it ran is found."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mcrs.experiment.util.untrusted import UntrustedInput, read_yaml


@dataclass(frozen=True)
class EvaluationRow:
    """One policy's results in one ``mcrs-eval`` run (one row of its ``metrics.csv``)."""

    path: Path
    policy: str
    env_name: str
    comm_range: float
    seed: int
    episodes: int
    means: dict[str, float]
    label: str | None = None  # a trained policy's label, kept by its record (the checkpoint may be gone)
    run: str | None = None  # a trained policy's <experiment>/<run folder> (records made before it: None)
    env: dict[str, Any] | None = None  # the scenario it ran (the evaluation's env config); None if unknown

    @property
    def is_heuristic(self) -> bool:
        return is_heuristic_policy(self.policy)


def is_heuristic_policy(policy: str) -> bool:
    """A heuristic's name, as opposed to a checkpoint or run directory given to ``mcrs-eval policy=``."""
    return "/" not in policy and not policy.endswith(".pt")


def env_node(config: Any) -> dict[str, Any] | None:
    """The ``env`` node of an evaluation's config, or None when there is none."""
    env = config.get("env") if isinstance(config, dict) else None
    return env if isinstance(env, dict) else None


def evaluation_config(result_dir: Path) -> Any:
    """The config an ``mcrs-eval`` result ran with (``.hydra/config.yaml``, read bounded), or None."""
    path = result_dir / ".hydra" / "config.yaml"
    with contextlib.suppress(UntrustedInput):
        return read_yaml(path, interpolations=False) if path.is_file() else None
    return None
