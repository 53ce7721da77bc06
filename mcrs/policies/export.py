"""A trained agent as one self-contained file: a ``torch.export`` program that runs without mcrs.

``export_agent`` writes :class:`~mcrs.policies.trained.GreedyAgentStep` of a checkpoint as a ``.pt2``
archive (``torch.export.save``) with a JSON description beside the program (``extra/mcrs.json``: the task
it was trained on, the action table, the inputs and outputs). On a vehicle, or in any other program::

    import torch
    step = torch.export.load("agent.pt2").module()
    action, hidden = step(observation, action_mask, last_action, hidden)

``load_exported`` reads such a file back with its description, refusing by name a file that is not one;
``mcrs-eval policy=agent.pt2`` scores it, so the file that is deployed is the file that was evaluated.
"""

from __future__ import annotations

import json
import os
import tempfile
import warnings
import zipfile
from pathlib import Path
from typing import Any

import torch

from mcrs.env.config import EnvConfig, from_mapping
from mcrs.env.core import MOVES, N_ACTIONS
from mcrs.env.layout import ObservationLayout
from mcrs.experiment.untrusted import check_archive
from mcrs.policies.trained import (
    EXPORTED_SUFFIX,
    OBSERVATION_FIELDS,
    GreedyAgentStep,
    TrainedPolicy,
    check_playable,
    load_trained_agent,
)

SUFFIX = EXPORTED_SUFFIX
FORMAT = "mcrs-exported-agent"
VERSION = 1
DESCRIPTION = "mcrs.json"  # the archive's extra file that describes the program
#: The most environments one call of the exported program takes (torch.export needs a bound).
MAX_ENVS = 1 << 16

INPUTS = {
    "observation": "[E, N, obs_dim] float32: each UAV's observation (observation_layout: the slices)",
    "action_mask": "[E, N, n_actions] bool: the moves allowed this step",
    "last_action": "[E, N] int64: each UAV's previous action, -1 at an episode's first step",
    "hidden": "[E, N, hidden_dim] float32: the returned hidden state, zeros at an episode's first step",
}
OUTPUTS = {
    "action": "[E, N] int64: the best allowed move of each UAV (moves[action] = (dx, dy))",
    "hidden": "[E, N, hidden_dim] float32: pass it back at the next step",
}


class ExportError(ValueError):
    """A file that is not an exported mcrs agent, or an export that cannot be written."""


def description(trained_env: EnvConfig, config: dict[str, Any], source: Path, env_steps: int | None) -> dict:
    """What ``mcrs.json`` says: enough to build the inputs and read the outputs without mcrs."""
    layout = ObservationLayout.from_config(trained_env)
    slices = {
        name: [part.start, part.stop]
        for name, part in vars(layout).items()
        if isinstance(part, slice) and part.stop > part.start
    }
    return {
        "format": FORMAT,
        "version": VERSION,
        "source": str(source),
        "env_steps": env_steps,
        "algo": config.get("algo", {}).get("name"),
        "seed": config.get("seed"),
        "env": trained_env.scenario(),
        "n_agents": trained_env.n_uavs,
        "obs_dim": trained_env.obs_dim,
        "n_actions": N_ACTIONS,
        "hidden_dim": int(config["model"]["hidden_dim"]),
        "moves": [list(move) for move in MOVES],
        "observation_layout": slices,
        "inputs": INPUTS,
        "outputs": OUTPUTS,
    }


def export_agent(policy: str | Path, out: str | Path, overwrite: bool = False) -> Path:
    """Write the agent of the checkpoint ``policy`` (a ``.pt`` file or a run directory) to ``out``
    (``.pt2``), atomically: a failure leaves no file, or the old one, behind."""
    out = Path(out).expanduser()
    if out.suffix != SUFFIX:
        raise ExportError(f"out={out}: an exported agent's file name ends in {SUFFIX}")
    if out.exists() and not overwrite:
        raise ExportError(f"out={out} exists: pass --force to replace it")
    if not out.parent.is_dir():
        raise ExportError(f"out={out}: the folder {out.parent} does not exist")
    trained = load_trained_agent(policy)
    step = GreedyAgentStep(trained.agent.cpu())
    E, N, H = 2, trained.env.n_uavs, trained.agent.hidden_dim
    example = (
        torch.zeros(E, N, trained.env.obs_dim),
        torch.ones(E, N, N_ACTIONS, dtype=torch.bool),
        torch.full((E, N), -1, dtype=torch.int64),
        torch.zeros(E, N, H),
    )
    envs = torch.export.Dim("envs", min=1, max=MAX_ENVS)
    with warnings.catch_warnings():  # nn.GRU re-points its flat weights while traced: harmless here
        warnings.filterwarnings("ignore", message=".*were assigned during export.*")
        program = torch.export.export(step, example, dynamic_shapes=tuple({0: envs} for _ in example))
    text = json.dumps(description(trained.env, trained.config, trained.path, trained.env_steps), indent=1)
    fd, tmp = tempfile.mkstemp(prefix=f".{out.stem}.", suffix=f".tmp{SUFFIX}", dir=out.parent)
    os.close(fd)
    try:
        torch.export.save(program, tmp, extra_files={DESCRIPTION: text})
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return out


def read_description(path: str | Path) -> dict[str, Any]:
    """The ``mcrs.json`` of the exported agent ``path``, read from the archive without loading the
    program; refuses (ExportError) a file that is not an exported mcrs agent of this version."""
    path = Path(path).expanduser()
    try:
        if not path.is_file():
            raise ExportError(f"exported agent {path} does not exist")
        refused = check_archive(path)
        if refused is None:
            with zipfile.ZipFile(path) as archive:
                names = [n for n in archive.namelist() if n.split("/", 1)[-1] == f"extra/{DESCRIPTION}"]
                text = archive.read(names[0]) if len(names) == 1 else None
    except OSError as error:
        raise ExportError(f"exported agent {path} cannot be read: {error.strerror or error}") from None
    if refused is not None:
        raise ExportError(f"exported agent {path} cannot be read safely: {refused}")
    if text is None:
        raise ExportError(
            f"{path} is not an exported mcrs agent (no extra/{DESCRIPTION}; make one with mcrs-export)"
        )
    try:
        meta = json.loads(text)
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ExportError(f"{path}: its {DESCRIPTION} is not JSON ({error})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ExportError(f"{path} is not an exported mcrs agent (no '{FORMAT}' marker in {DESCRIPTION})")
    if meta.get("version") != VERSION:
        raise ExportError(f"{path} has export version {meta.get('version')}; this mcrs reads {VERSION}")
    return meta


def load_exported(path: str | Path) -> tuple[torch.nn.Module, dict[str, Any]]:
    """The program of the exported agent ``path`` (a callable module) and its description."""
    meta = read_description(path)
    try:
        program = torch.export.load(Path(path).expanduser())
    except Exception as error:  # a damaged program inside a sane archive
        first = (str(error).strip().splitlines() or [type(error).__name__])[0]
        raise ExportError(f"exported agent {path}: its program cannot be loaded: {first}") from None
    return program.module(), meta


def exported_policy(path: str | Path, env_config: EnvConfig, seed: int = 0) -> TrainedPolicy:
    """The exported agent ``path`` as a policy of ``env_config`` (which must be the map and team it was
    trained on), on the CPU: ``mcrs-eval`` and ``mcrs-render`` play it like a checkpoint."""
    if env_config.device != "cpu":
        raise ExportError(f"exported agent {path}: played on the CPU only (env.device={env_config.device})")
    step, meta = load_exported(path)
    try:
        trained = from_mapping(meta["env"])
        hidden_dim = int(meta["hidden_dim"])
    except (KeyError, TypeError, ValueError) as error:
        raise ExportError(f"{path}: its {DESCRIPTION} lacks a usable env or hidden_dim ({error})") from None
    check_playable(trained, env_config, f"exported agent {path}")
    return TrainedPolicy(env_config, step, hidden_dim, seed)


def observation_settings(path: str | Path) -> dict[str, Any]:
    """The exported agent's values of the observation fields (``mcrs.policies.policy_env``); none when its
    description has no usable env (loading the policy then names the problem)."""
    try:
        trained = from_mapping(read_description(path)["env"])
    except (KeyError, TypeError, ValueError):  # ExportError is a ValueError
        return {}
    return {name: getattr(trained, name) for name in OBSERVATION_FIELDS}
