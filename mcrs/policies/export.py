"""A trained agent as one self-contained ``torch.export`` program that runs without mcrs.

``export_agent`` writes a checkpoint's :class:`~mcrs.policies.trained.GreedyAgentStep` as a ``.pt2``
archive with a JSON description (``extra/mcrs.json``: the task, the action table, the inputs and outputs),
then loads it back and checks that it computes what the checkpoint computes. In any program::

    import torch
    step = torch.export.load("agent.pt2").module()
    action, hidden = step(observation, action_mask, last_action, hidden)

The mcrs tools never run a ``.pt2``'s program, because ``torch.export.load`` unpickles parts of the archive
and executes Python stored in it. ``mcrs-eval`` and ``mcrs-render`` read the description and the raw
float32 weight bytes instead (:func:`read_weights`). :func:`load_exported` is ``torch.export.load`` after
the same checks, for files you made."""

from __future__ import annotations

import glob
import json
import math
import os
import re
import shutil
import socket
import tempfile
import warnings
import zipfile
from pathlib import Path
from typing import Any

import torch

from mcrs.env.config import EnvConfig, from_mapping
from mcrs.env.core import MOVES, N_ACTIONS
from mcrs.env.layout import ObservationLayout
from mcrs.experiment.util.untrusted import check_archive
from mcrs.models.agent import RecurrentAgent
from mcrs.policies.task_runs import load_task_run, task_description, task_node
from mcrs.policies.trained import (
    EXPORTED_SUFFIX,
    OBSERVATION_FIELDS,
    GreedyAgentStep,
    TrainedPolicy,
    check_playable,
    load_trained_agent,
)

FORMAT = "mcrs-exported-agent"
VERSION = 1
DESCRIPTION = "mcrs.json"  # the archive's extra file that describes the program
#: The most environments one call of the exported program takes (torch.export needs a bound).
MAX_ENVS = 1 << 16
#: The members of an archive that ``torch.export.save`` writes for one program with no constants, below
#: its one top folder: anything else (AOTInductor libraries, pickled payloads, legacy files) is refused.
MEMBERS = re.compile(
    r"(archive_format|archive_version|byteorder|\.data/version|\.data/serialization_id|models/model\.json"
    r"|data/weights/model_weights_config\.json|data/weights/weight_\d+"
    r"|data/constants/model_constants_config\.json|data/sample_inputs/model\.pt|extra/mcrs\.json)"
)
FLOAT32, STRIDED = 7, 7  # torch._export.serde.schema's ScalarType.FLOAT and Layout.Strided
#: The agent's tensors as ``torch.export`` names them (``GreedyAgentStep.agent``'s state dict).
AGENT_WEIGHTS = tuple(
    f"agent.{name}"
    for name in ("fc1.weight", "fc1.bias", "rnn.weight_ih_l0", "rnn.weight_hh_l0", "rnn.bias_ih_l0",
                 "rnn.bias_hh_l0", "fc2.weight", "fc2.bias")
)  # fmt: skip
#: The description's fields a user builds the inputs and reads the outputs by: checked against the agent.
INTERFACE = (
    "n_agents",
    "obs_dim",
    "n_actions",
    "hidden_dim",
    "moves",
    "observation_layout",
    "inputs",
    "outputs",
)
#: The largest JSON member read (``mcrs.json``, the weight index): an honest one is a few kB.
MAX_JSON_BYTES = 1 << 20

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
    """Return what ``mcrs.json`` says: enough to build the inputs and read the outputs without mcrs."""
    layout = ObservationLayout.from_config(trained_env)
    slices = {
        name: [part.start, part.stop]
        for name, part in vars(layout).items()
        if isinstance(part, slice) and part.stop > part.start
    }
    model = config["model"]
    return {
        "format": FORMAT,
        "version": VERSION,
        "source": str(source),
        "env_steps": env_steps,
        "algo": config.get("algo", {}).get("name"),
        "seed": config.get("seed"),
        "env": trained_env.scenario(),
        "model": {key: model[key] for key in ("hidden_dim", "agent_id", "last_action")},
        "n_agents": trained_env.n_uavs,
        "obs_dim": trained_env.obs_dim,
        "n_actions": N_ACTIONS,
        "hidden_dim": int(model["hidden_dim"]),
        "moves": [list(move) for move in MOVES],
        "observation_layout": slices,
        "inputs": INPUTS,
        "outputs": OUTPUTS,
    }


def _example_inputs(
    E: int, n_agents: int, obs_dim: int, hidden_dim: int, seed: int, n_actions: int = N_ACTIONS
) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    mask = torch.rand(E, n_agents, n_actions, generator=g) > 0.5
    mask[..., 0] = True
    return (
        torch.rand(E, n_agents, obs_dim, generator=g) * 2 - 1,
        mask,
        torch.randint(-1, n_actions, (E, n_agents), generator=g),
        torch.randn(E, n_agents, hidden_dim, generator=g),
    )


def export_agent(policy: str | Path, out: str | Path, overwrite: bool = False) -> Path:
    """Write the agent of the checkpoint or run directory ``policy`` to ``out`` (``.pt2``), atomically. The
    file is kept only once it has been loaded back and has computed the checkpoint's actions and hidden
    states."""
    out = Path(out).expanduser()
    if out.suffix != EXPORTED_SUFFIX:
        raise ExportError(f"out={out}: an exported agent's file name ends in {EXPORTED_SUFFIX}")
    if out.exists() and not overwrite:
        raise ExportError(f"out={out} exists: pass --force to replace it")
    if not out.parent.is_dir():
        raise ExportError(f"out={out}: the folder {out.parent} does not exist")
    if task_node(policy) is not None:  # a run of another task: its agent fits its task (mcrs.json says which)
        run = load_task_run(policy)
        step = GreedyAgentStep(run.agent.cpu())
        shape = (run.task.n_agents, run.task.obs_dim, run.agent.hidden_dim)
        n_actions, meta = run.task.n_actions, task_description(run, FORMAT, VERSION)
    else:
        trained = load_trained_agent(policy)
        step = GreedyAgentStep(trained.agent.cpu())
        shape = (trained.env.n_uavs, trained.env.obs_dim, trained.agent.hidden_dim)
        n_actions = N_ACTIONS
        meta = description(trained.env, trained.config, trained.path, trained.env_steps)
    envs = torch.export.Dim("envs", min=1, max=MAX_ENVS)
    with warnings.catch_warnings():  # nn.GRU re-points its flat weights while traced: harmless here
        warnings.filterwarnings("ignore", message=".*were assigned during export.*")
        program = torch.export.export(
            step,
            _example_inputs(2, *shape, seed=0, n_actions=n_actions),
            dynamic_shapes=tuple({0: envs} for _ in range(4)),
        )
    text = json.dumps(meta, indent=1)
    folder = _temporary_folder(out)
    try:
        tmp = folder / out.name  # the archive's top folder is named after the file
        torch.export.save(program, tmp, extra_files={DESCRIPTION: text})
        _check_written(tmp, step, shape, n_actions)
        os.replace(tmp, out)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return out


def _temporary_folder(out: Path) -> Path:
    """Return a hidden folder beside ``out`` for the archive being written, named with this host and process
    id. It first removes folders that killed exports of ``out`` left: this host's, whose process is gone
    and which hold nothing but ``out``'s archive."""
    host = host_tag()
    mine = re.compile(rf"\.{re.escape(out.stem)}\.{re.escape(host)}-(\d+)\.[A-Za-z0-9_]+\.tmp")
    for stale in out.parent.glob(f".{glob.escape(out.stem)}.*.tmp"):
        found = mine.fullmatch(stale.name)
        if found is None or int(found[1]) == os.getpid() or _alive(int(found[1])):
            continue
        try:
            if stale.is_dir() and not stale.is_symlink() and set(os.listdir(stale)) <= {out.name}:
                shutil.rmtree(stale, ignore_errors=True)
        except OSError:  # unreadable: not ours to judge
            continue
    return Path(tempfile.mkdtemp(prefix=f".{out.stem}.{host}-{os.getpid()}.", suffix=".tmp", dir=out.parent))


def host_tag() -> str:
    """Return this machine's name as a file-name part, since hosts may share a disk."""
    return re.sub(r"[^A-Za-z0-9_-]", "_", socket.gethostname())[:64] or "host"


def _alive(pid: int) -> bool:
    """Whether process ``pid`` exists, another user's included."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return True


@torch.no_grad()
def _check_written(
    path: Path, step: GreedyAgentStep, shape: tuple[int, int, int], n_actions: int = N_ACTIONS
) -> None:
    """Check that the written file computes ``step``'s outputs and that its weights read back are ``step``'s."""
    program, _, weights = _load(path)
    for E in (1, 3):
        args = _example_inputs(E, *shape, seed=E, n_actions=n_actions)
        for got, want in zip(program(*args), step(*args), strict=True):
            if not torch.equal(got, want):
                raise ExportError(f"{path}: the exported program does not compute the agent's step (E={E})")
    if any(not torch.equal(weights[k], v) for k, v in step.agent.state_dict().items()):
        raise ExportError(f"{path}: the weights read back differ from the agent's")


def _members(archive: zipfile.ZipFile, path: Path) -> dict[str, zipfile.ZipInfo]:
    """Return the archive's members by their name below the top folder. It refuses a member :data:`MEMBERS`
    does not name, and a name given twice, since zip readers disagree on which copy counts."""
    names: dict[str, zipfile.ZipInfo] = {}
    for member in archive.infolist():
        name = member.filename.split("/", 1)[-1]
        if MEMBERS.fullmatch(name) is None:
            raise ExportError(
                f"exported agent {path}: unexpected archive member {member.filename!r} (an mcrs export holds "
                "one torch.export program, its raw float32 weights and mcrs.json; nothing pickled or compiled)"
            )
        if name in names:
            raise ExportError(f"exported agent {path}: the archive member {member.filename!r} is there twice")
        names[name] = member
    return names


def _read(archive: zipfile.ZipFile, member: zipfile.ZipInfo, path: Path, limit: int | None = None) -> bytes:
    """Return a member's bytes, refusing by name a damaged or encrypted member or one over ``limit`` bytes."""
    if limit is not None and member.file_size > limit:
        raise ExportError(
            f"exported agent {path}: {member.filename} holds {member.file_size:,} bytes (at most {limit:,})"
        )
    try:
        return archive.read(member)
    except (OSError, EOFError, RuntimeError, NotImplementedError, zipfile.BadZipFile) as error:
        raise ExportError(f"exported agent {path}: {member.filename} cannot be read ({error})") from None


def _json(archive: zipfile.ZipFile, member: zipfile.ZipInfo, path: Path) -> Any:
    try:
        return json.loads(_read(archive, member, path, MAX_JSON_BYTES))
    except (ValueError, RecursionError) as error:  # JSONDecodeError, UnicodeDecodeError, 5000-digit ints
        reason = "nested too deep" if isinstance(error, RecursionError) else error
        raise ExportError(f"exported agent {path}: {member.filename} is not JSON ({reason})") from None


def _open(path: Path) -> zipfile.ZipFile:
    """Return the archive ``path`` after :func:`check_archive`, refusing a file that is not a sane zip."""
    try:
        if not path.is_file():
            raise ExportError(f"exported agent {path} does not exist")
        refused = check_archive(path)
        if refused is None:
            return zipfile.ZipFile(path)
    except (OSError, zipfile.BadZipFile, RuntimeError, EOFError) as error:
        raise ExportError(
            f"exported agent {path} cannot be read: {getattr(error, 'strerror', None) or error}"
        ) from None
    raise ExportError(f"exported agent {path} cannot be read safely: {refused}")


def read_description(path: str | Path) -> dict[str, Any]:
    """Return the ``mcrs.json`` of the exported agent ``path`` without loading the program; raise ExportError
    for other files."""
    path = Path(path).expanduser()
    with _open(path) as archive:
        return _description(archive, path)


def _description(archive: zipfile.ZipFile, path: Path) -> dict[str, Any]:
    key = f"extra/{DESCRIPTION}"
    if not any(n.split("/", 1)[-1] == key for n in archive.namelist()):
        raise ExportError(
            f"{path} is not an exported mcrs agent (no extra/{DESCRIPTION}; make one with mcrs-export)"
        )
    meta = _json(archive, _members(archive, path)[key], path)
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ExportError(f"{path} is not an exported mcrs agent (no '{FORMAT}' marker in {DESCRIPTION})")
    if meta.get("version") != VERSION:
        raise ExportError(
            f"{path} has export version {str(meta.get('version'))[:20]}; this mcrs reads {VERSION}"
        )
    return meta


def _plain_float32(fqn: str, entry: Any) -> tuple[list[int], str] | None:
    """Return the sizes and member of a plain contiguous 1-D or 2-D float32 weight entry, or None for anything
    else."""
    try:
        meta = entry["tensor_meta"]
        if len(meta["sizes"]) not in (1, 2) or len(meta["strides"]) != len(meta["sizes"]):
            return None
        sizes = [int(s["as_int"]) for s in meta["sizes"]]
        strides = [int(s["as_int"]) for s in meta["strides"]]
        plain = (
            fqn in AGENT_WEIGHTS
            and entry["use_pickle"] is False
            and meta["dtype"] == FLOAT32
            and meta["layout"] == STRIDED
            and int(meta["storage_offset"]["as_int"]) == 0
            and all(size >= 0 for size in sizes)
            and strides == ([sizes[1], 1] if len(sizes) == 2 else [1])
            and isinstance(entry["path_name"], str)
        )
    except (KeyError, TypeError, ValueError, OverflowError):
        return None
    return (sizes, f"data/weights/{entry['path_name']}") if plain else None


def read_weights(path: str | Path) -> dict[str, torch.Tensor]:
    """Return the agent's weights in ``path`` as raw little-endian float32, named as :class:`RecurrentAgent`
    names them. Nothing is unpickled: each tensor must be in a member of its own of exactly its size, and
    anything else is refused by name."""
    path = Path(path).expanduser()
    with _open(path) as archive:
        return _weights(archive, path)


def _weights(archive: zipfile.ZipFile, path: Path) -> dict[str, torch.Tensor]:
    members = _members(archive, path)
    needed = (
        "byteorder",
        "data/weights/model_weights_config.json",
        "data/constants/model_constants_config.json",
    )
    missing = [name for name in needed if name not in members]
    if missing:
        raise ExportError(f"exported agent {path}: no {missing[0]} in the archive")
    order = _read(archive, members["byteorder"], path, 16)
    config = _json(archive, members[needed[1]], path)
    constants = _json(archive, members[needed[2]], path)
    if order != b"little" or constants != {"config": {}}:
        raise ExportError(
            f"exported agent {path}: not the little-endian, constant-free program mcrs-export writes"
        )
    entries = config.get("config") if isinstance(config, dict) else None
    if not isinstance(entries, dict) or sorted(entries) != sorted(AGENT_WEIGHTS):
        extra = sorted(set(entries) - set(AGENT_WEIGHTS)) if isinstance(entries, dict) else []
        missing = sorted(set(AGENT_WEIGHTS) - set(entries)) if isinstance(entries, dict) else AGENT_WEIGHTS
        raise ExportError(
            f"exported agent {path}: its weight index is not the agent's {len(AGENT_WEIGHTS)} tensors "
            f"(unexpected: {str(extra[:2])[:100]}{' ...' if len(extra) > 2 else ''}; missing: {list(missing)})"
        )
    weights, used = {}, set()
    for fqn, entry in entries.items():
        plain = _plain_float32(fqn, entry)
        member = members.get(plain[1]) if plain is not None else None
        if plain is None or member is None or plain[1] in used or member.file_size != 4 * math.prod(plain[0]):
            raise ExportError(
                f"exported agent {path}: weight {fqn!r} is not a plain float32 tensor of its own"
            )
        used.add(plain[1])
        data = _read(archive, member, path)
        weights[fqn.removeprefix("agent.")] = torch.frombuffer(bytearray(data), dtype=torch.float32).view(
            plain[0]
        )
    return weights


def _trained_env(path: Path, meta: dict[str, Any]) -> EnvConfig:
    """Return the validated scenario the description says the agent was trained on."""
    try:
        env = meta["env"]
        name = env["name"]
        if not isinstance(name, str) or not name.isprintable() or len(name) > 64:
            raise ValueError(f"name {name!r:.40}: not a printable name of at most 64 characters")
        return from_mapping(env)
    except (KeyError, TypeError, ValueError, OverflowError) as error:  # 10**400 overflows float()
        raise ExportError(f"{path}: its {DESCRIPTION} lacks a usable env ({str(error)[:200]})") from None


def _agent(
    path: Path, meta: dict[str, Any], trained: EnvConfig, weights: dict[str, torch.Tensor]
) -> RecurrentAgent:
    """Build the agent of ``path`` from its description and raw weights, checking sizes before allocating
    anything."""
    try:
        model = meta["model"]
        hidden_dim, agent_id, last_action = (
            int(model["hidden_dim"]),
            bool(model["agent_id"]),
            bool(model["last_action"]),
        )
    except (KeyError, TypeError, ValueError) as error:
        raise ExportError(f"{path}: its {DESCRIPTION} lacks a usable model ({error})") from None
    inputs = trained.obs_dim + (N_ACTIONS if last_action else 0) + (trained.n_uavs if agent_id else 0)
    first = weights.get("fc1.weight")
    if first is None or tuple(first.shape) != (hidden_dim, inputs):
        raise ExportError(
            f"exported agent {path}: its weights do not fit its description (fc1.weight "
            f"{None if first is None else tuple(first.shape)}, described ({hidden_dim}, {inputs}))"
        )
    agent = RecurrentAgent(trained.obs_dim, N_ACTIONS, trained.n_uavs, hidden_dim, agent_id, last_action)
    try:
        agent.load_state_dict(weights)
    except RuntimeError as error:
        reason = (str(error).strip().splitlines() or ["?"])[0]
        raise ExportError(
            f"exported agent {path}: its weights do not fit its description: {reason}"
        ) from None
    bad = [k for k, v in weights.items() if not torch.isfinite(v).all()]
    if bad:
        raise ExportError(f"exported agent {path}: the weights {', '.join(bad[:3])} hold NaN or inf")
    return agent.eval()


def load_exported(path: str | Path) -> tuple[torch.nn.Module, dict[str, Any]]:
    """Return the program of the exported agent ``path`` and its description, after the checks of
    :func:`read_description` and :func:`read_weights`. Loading a program runs code stored in the file: use
    it only on files you trust."""
    program, meta, _ = _load(Path(path).expanduser())
    return program, meta


def _load(path: Path) -> tuple[torch.nn.Module, dict[str, Any], dict[str, torch.Tensor]]:
    """Run :func:`load_exported` and also return the weights its checks read."""
    with _open(path) as archive:
        meta, weights = _description(archive, path), _weights(archive, path)
    try:
        program = torch.export.load(path)
    except Exception as error:  # a damaged program inside a sane archive
        first = (str(error).strip().splitlines() or [type(error).__name__])[0]
        raise ExportError(f"exported agent {path}: its program cannot be loaded: {first}") from None
    return program.module(), meta, weights


def exported_policy(path: str | Path, env_config: EnvConfig, seed: int = 0) -> TrainedPolicy:
    """Return the exported agent ``path`` as a policy of ``env_config``, which must have its map and team. The
    weights run in mcrs's own step, so no code from the file runs."""
    path = Path(path).expanduser()
    with _open(path) as archive:
        meta = _description(archive, path)
        if isinstance(meta.get("task"), dict):  # its task's env is rebuilt from its run, not from a file
            raise ExportError(
                f"exported agent {path} plays the task {meta['task'].get('name') or meta['task'].get('_target_')!r}, "
                "not MCRS: evaluate the run it came from (mcrs-eval policy=<run>)"
            )
        trained = _trained_env(path, meta)
        check_playable(trained, env_config, f"exported agent {path}")  # first: the sizes are then the env's
        agent = _agent(path, meta, trained, _weights(archive, path))
    interface = description(trained, {"model": meta["model"]}, Path(), None)
    wrong = [k for k in INTERFACE if meta.get(k) != interface[k]]
    if wrong:  # a reader without mcrs would build its inputs or read its actions from these
        raise ExportError(
            f"exported agent {path}: its {DESCRIPTION} has a wrong {wrong[0]} for its agent and env"
        )
    agent = agent.to(env_config.device)
    return TrainedPolicy(env_config, GreedyAgentStep(agent), agent.hidden_dim, seed)


def trained_env(path: str | Path) -> EnvConfig | None:
    """Return the env config the description says the agent was trained on, or None when it has no usable one."""
    try:
        return _trained_env(Path(path).expanduser(), read_description(path))
    except ValueError:  # ExportError is one: loading the policy names the problem
        return None


def observation_settings(path: str | Path) -> dict[str, Any]:
    """Return the exported agent's values of the observation fields; none without a usable env."""
    trained = trained_env(path)
    return {} if trained is None else {name: getattr(trained, name) for name in OBSERVATION_FIELDS}
