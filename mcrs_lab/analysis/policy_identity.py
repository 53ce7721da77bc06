"""What names a policy in the records and the reports: a heuristic's own name, or for a trained one its
label (``trained qmix``, from its run's config) and its run (``<experiment>/<run folder>``).

The run tells apart two experiments' runs of one folder name (``shields_gamma/map20_qmix_gamma0.5_seed0`` and
``shields_view/map20_qmix_gamma0.5_seed0``): an evaluation record keeps both (mcrs_lab.analysis.records), so
its file name and the report's method name do not depend on the checkpoint still being there.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from mcrs.experiment.util.untrusted import UntrustedInput, read_yaml
from mcrs.policies.export import ExportError, read_description
from mcrs.policies.trained import EXPORTED_SUFFIX
from mcrs_lab.analysis.runs import is_heuristic_policy

#: An algorithm name read from an exported agent's description: it becomes part of a record's file name.
ALGO_NAME = re.compile(r"[a-z][a-z0-9_]{0,31}")


def _run_config(policy: str) -> tuple[Path, dict[str, Any]] | None:
    """The training run a checkpoint or run directory belongs to, and its ``config.yaml`` (bounded before it
    is parsed); None when there is none or it is not a readable mapping."""
    path = Path(policy)
    for run_dir in (path, path.parent, path.parent.parent):
        config = run_dir / "config.yaml"
        if config.is_file():
            try:
                values = read_yaml(config, interpolations=False)
            except UntrustedInput:
                return None
            return (run_dir, values) if isinstance(values, dict) else None
    return None


def policy_label(policy: str) -> str:
    """A heuristic's name, or ``trained <algo>`` for a checkpoint (read from its run's config; without one,
    the file's name)."""
    if is_heuristic_policy(policy):
        return policy
    found = _run_config(policy)
    algo = found[1].get("algo") if found else None
    name = algo.get("name") if isinstance(algo, dict) else _exported_algo(policy)
    return f"trained {name}" if isinstance(name, str) and name else f"trained {Path(policy).stem}"


def _exported_algo(policy: str) -> str | None:
    """The algorithm an exported agent (``.pt2``, ``mcrs-export``) names in its description, when it is a
    plain name; None for anything else (the description is read without running the file's program)."""
    if not policy.endswith(EXPORTED_SUFFIX):
        return None
    try:
        algo = read_description(policy).get("algo")
    except ExportError:
        return None
    return algo if isinstance(algo, str) and ALGO_NAME.fullmatch(algo) else None


def trained_run_id(policy: str) -> str | None:
    """``<experiment>/<run folder>`` of a checkpoint's training run (the campaign's point id), or None for
    a heuristic, or a run whose config is not found or names no experiment."""
    if is_heuristic_policy(policy):
        return None
    found = _run_config(policy)
    if found is None:
        return None
    run_dir, config = found
    experiment = config.get("experiment")
    return f"{experiment}/{run_dir.name}" if isinstance(experiment, str) and experiment else None
