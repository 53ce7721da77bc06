"""``mcrs-export``: a trained agent as a ``torch.export`` file that runs without mcrs and plays as the
checkpoint it came from."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import warnings
import zipfile
from pathlib import Path

import pytest
import torch

from mcrs.env import scenario
from mcrs.env.layout import ObservationLayout
from mcrs.evaluate import evaluate_policy, policy_names
from mcrs.experiment.training.trainer import Experiment
from mcrs.export_agent import main as export_main
from mcrs.policies import export
from mcrs.policies.trained import GreedyAgentStep, load_trained_agent
from tests.train_helpers import compose_config


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("run")
    Experiment(compose_config("train.total_env_steps=80", "env=map10"), path).run()
    return path


@pytest.fixture(scope="module")
def exported(run_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return export.export_agent(run_dir, tmp_path_factory.mktemp("export") / "agent.pt2")


def _inputs(E: int, N: int, obs_dim: int, hidden: int, seed: int) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    mask = torch.rand(E, N, 8, generator=g) > 0.3
    mask[..., 0] = True  # every agent has an allowed move
    return (
        torch.rand(E, N, obs_dim, generator=g),
        mask,
        torch.randint(-1, 8, (E, N), generator=g),
        torch.randn(E, N, hidden, generator=g),
    )


def test_the_exported_program_computes_the_checkpoints_greedy_step(run_dir: Path, exported: Path) -> None:
    step, meta = export.load_exported(exported)
    reference = GreedyAgentStep(load_trained_agent(run_dir).agent)
    for E in (1, 5):  # any number of environments, not only the traced example's
        args = _inputs(E, meta["n_agents"], meta["obs_dim"], meta["hidden_dim"], seed=E)
        action, hidden = step(*args)
        with torch.no_grad():
            expected_action, expected_hidden = reference(*args)
        assert action.dtype == torch.int64 and action.shape == (E, meta["n_agents"])
        assert torch.equal(action, expected_action)
        assert torch.equal(hidden, expected_hidden)
        assert bool(args[1].gather(-1, action.unsqueeze(-1)).all())  # only allowed moves


def test_each_agents_row_is_its_own(exported: Path) -> None:
    """What the description promises a single vehicle: its row's output depends on its row's inputs only."""
    step, meta = export.load_exported(exported)
    args = _inputs(3, meta["n_agents"], meta["obs_dim"], meta["hidden_dim"], seed=0)
    others = _inputs(3, meta["n_agents"], meta["obs_dim"], meta["hidden_dim"], seed=1)
    mixed = tuple(torch.cat([a[:, :1], b[:, 1:]], dim=1) for a, b in zip(args, others, strict=True))
    action, hidden = step(*args)
    mixed_action, mixed_hidden = step(*mixed)
    assert torch.equal(action[:, 0], mixed_action[:, 0])
    assert torch.allclose(hidden[:, 0], mixed_hidden[:, 0], rtol=0, atol=1e-6)
    assert not torch.equal(hidden[:, 1:], mixed_hidden[:, 1:])  # the other rows did change


def test_the_description_says_how_to_build_the_inputs(run_dir: Path, exported: Path) -> None:
    meta = export.read_description(exported)
    env = scenario("map10")
    layout = ObservationLayout.from_config(env)
    assert meta["env"]["name"] == "map10" and meta["n_agents"] == env.n_uavs == 4
    assert meta["obs_dim"] == env.obs_dim and meta["n_actions"] == len(meta["moves"]) == 8
    assert meta["observation_layout"]["no_fly"] == [layout.no_fly.start, layout.no_fly.stop]
    assert meta["algo"] == "qmix" and meta["env_steps"] == load_trained_agent(run_dir).env_steps > 0
    assert set(meta["inputs"]) == {"observation", "action_mask", "last_action", "hidden"}


def test_the_file_runs_in_a_process_without_mcrs(exported: Path) -> None:
    script = f"""
import sys, torch
step = torch.export.load({str(exported)!r}).module()
n = 4
action, hidden = step(torch.zeros(2, n, 36), torch.ones(2, n, 8, dtype=torch.bool),
                      torch.full((2, n), -1), torch.zeros(2, n, 16))
assert not [m for m in sys.modules if m == "mcrs" or m.startswith("mcrs.")], "mcrs was imported"
print(tuple(action.shape), tuple(hidden.shape))
"""
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd="/")
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "(2, 4) (2, 4, 16)"


def test_mcrs_eval_scores_the_file_as_the_checkpoint(run_dir: Path, exported: Path) -> None:
    env_config = scenario("map10", max_steps=10)
    ours = evaluate_policy(env_config, str(exported), episodes=4, seed=3)
    theirs = evaluate_policy(env_config, str(run_dir), episodes=4, seed=3)
    assert ours == theirs
    with pytest.raises(ValueError, match=r"exported agent .* trained on map10.*pass env=map10"):
        evaluate_policy(scenario("map20"), str(exported), episodes=1, seed=0)


def test_the_command_writes_and_refuses_by_name(run_dir: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "a.pt2"
    assert export_main([str(run_dir), str(out)]) == 0
    assert "a.pt2" in capsys.readouterr().out
    before = out.read_bytes()
    assert export_main([str(run_dir), str(out)]) == 1  # exists
    assert "exists: pass --force" in capsys.readouterr().err and out.read_bytes() == before
    assert export_main([str(run_dir), str(tmp_path / "a.onnx")]) == 1
    assert "ends in .pt2" in capsys.readouterr().err
    assert export_main([str(run_dir), str(tmp_path / "missing" / "a.pt2")]) == 1
    assert "does not exist" in capsys.readouterr().err
    assert export_main([str(tmp_path / "no_run"), str(tmp_path / "b.pt2")]) == 1
    assert "checkpoint" in capsys.readouterr().err and not (tmp_path / "b.pt2").exists()
    assert export_main([str(run_dir), str(out), "--force"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.pt2"]  # no temporary left


def test_a_failed_write_leaves_the_old_file_and_no_temporary(
    run_dir: Path, exported: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "agent.pt2"
    out.write_bytes(exported.read_bytes())

    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch.export, "save", full_disk)
    assert export_main([str(run_dir), str(out), "--force"]) == 1
    assert out.read_bytes() == exported.read_bytes()
    assert [p.name for p in tmp_path.iterdir()] == ["agent.pt2"]


def test_a_killed_exports_temporary_folder_goes_with_the_next_export(run_dir: Path, tmp_path: Path) -> None:
    """SIGKILL skips the export's own clean-up: the next export to that file removes what the dead process
    left, and nothing that a live process, or anything but an export, holds."""
    gone = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True
    )
    dead, host = int(gone.stdout), export.host_tag()
    left = tmp_path / f".agent.{host}-{dead}.k2j4.tmp"  # as a killed export leaves it: a half-written archive
    left.mkdir()
    (left / "agent.pt2").write_bytes(b"PK half")
    kept = [
        f".agent.{host}-{os.getppid()}.x9z1.tmp",  # another export still writing
        f".agent.{host}-{dead}.mine.tmp",  # the pattern, but someone's own files (below)
        f".agent.other_host-{dead}.b2.tmp",  # another host's, on a shared disk: its process is not ours
        f".agent.7.{host}-{dead}.c3.tmp",  # a live export to agent.7.pt2 (the pid is not 7)
        f".other.{host}-{dead}.a1.tmp",  # another file's
    ]
    for name in kept:
        (tmp_path / name).mkdir()
    (tmp_path / kept[1] / "notes.txt").write_text("keep")
    assert export_main([str(run_dir), str(tmp_path / "agent.pt2")]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["agent.pt2", *kept])


def _rewritten(exported: Path, path: Path, description: bytes | None) -> Path:
    """``exported`` with its mcrs.json replaced by ``description`` (None: removed)."""
    with zipfile.ZipFile(exported) as source, zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as target:
        for member in source.infolist():
            if member.filename.endswith("extra/mcrs.json"):
                if description is not None:
                    target.writestr(member, description)
            else:
                target.writestr(member, source.read(member))
    return path


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (None, "does not exist"),
        (b"", "cannot be read safely"),
        (b"not a zip archive at all", "not a zip archive"),
        ("no description", r"not an exported mcrs agent \(no extra/mcrs.json"),
        (b"{not json", "is not JSON"),
        (json.dumps({"format": "something else"}).encode(), "no 'mcrs-exported-agent' marker"),
        (json.dumps({"format": "mcrs-exported-agent", "version": 99}).encode(), "export version 99"),
    ],
)
def test_a_file_that_is_not_an_exported_agent_is_refused_by_name(
    exported: Path, tmp_path: Path, content: bytes | str | None, message: str
) -> None:
    path = tmp_path / "bad.pt2"
    if content == "no description":
        _rewritten(exported, path, None)
    elif isinstance(content, bytes) and content.startswith(b"{"):
        _rewritten(exported, path, content)
    elif content is not None:
        path.write_bytes(content)
    with pytest.raises(export.ExportError, match=message):
        export.load_exported(path)
    if content is not None:  # mcrs-eval refuses it before any episode runs
        with pytest.raises(ValueError, match=message):
            policy_names(str(path))


def test_a_checkpoint_renamed_pt2_is_not_taken_for_an_export(run_dir: Path, tmp_path: Path) -> None:
    model = sorted((run_dir / "checkpoints").glob("model_*.pt"))[-1]
    renamed = tmp_path / "model.pt2"
    renamed.write_bytes(model.read_bytes())
    with pytest.raises(export.ExportError, match="not an exported mcrs agent"):
        export.exported_policy(renamed, scenario("map10"))


def test_a_refusal_is_one_line_and_an_exit_status(tmp_path: Path) -> None:
    out = subprocess.run(
        [sys.executable, "-m", "mcrs.export_agent", str(tmp_path / "no_run"), str(tmp_path / "a.pt2")],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 1
    assert out.stderr.startswith("mcrs-export: error: checkpoint ") and out.stderr.count("\n") == 1
    assert list(tmp_path.iterdir()) == []


def test_the_deployment_example_flies_each_uav_on_its_own(exported: Path) -> None:
    """examples/deploy_exported.py: every UAV calls the file with its own row and picks the team call's move."""
    example = Path(__file__).parents[1] / "examples" / "deploy_exported.py"
    out = subprocess.run(
        [sys.executable, str(example), str(exported), "--episodes", "1", "--seed", "4"],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stderr
    assert "episode 0 (seed 4): team reward" in out.stdout and "every UAV decided alone" in out.stdout


def _with_member(exported: Path, path: Path, edit) -> Path:
    """``exported`` rewritten member by member through ``edit(name, data) -> data | None`` (None: dropped),
    plus what ``edit(None, None)`` returns as extra ``(name, data)`` members."""
    with zipfile.ZipFile(exported) as source, zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as target:
        top = source.namelist()[0].split("/", 1)[0]
        for member in source.infolist():
            data = edit(member.filename.split("/", 1)[1], source.read(member))
            if data is not None:
                target.writestr(member, data)
        for name, data in edit(None, None) or []:
            target.writestr(f"{top}/{name}", data)
    return path


def test_the_tools_never_run_code_stored_in_the_file(exported: Path, tmp_path: Path) -> None:
    """torch.export.load executes a program's shape guards (Python text in models/model.json): mcrs-eval
    reads the weights instead, so a file whose guards run a command plays, and the command never runs."""
    marker = tmp_path / "ran"
    payload = f"__import__('pathlib').Path({str(marker)!r}).touch() is None"

    def poison(name, data):
        if name != "models/model.json":
            return None if name is None else data
        program = json.loads(data)
        program["guards_code"] = [payload]
        return json.dumps(program).encode()

    crafted = _with_member(exported, tmp_path / "crafted.pt2", poison)
    result = evaluate_policy(scenario("map10", max_steps=5), str(crafted), episodes=2, seed=0)
    assert result["episode_reward"][1] >= 0 and not marker.exists()
    export.load_exported(crafted)[0](*_inputs(1, 4, 36, 16, seed=0))  # the file's own program does run it
    assert marker.exists()


def _changed(member: str, change):
    """An edit for :func:`_with_member`: ``change(data)`` on one member, the others as they are."""
    return lambda n, d: None if n is None else (change(d) if n == member else d)


def _added(*members: tuple[str, bytes]):
    return lambda n, d: list(members) if n is None else d


def _weight_index(change):
    def edit(data: bytes) -> bytes:
        index = json.loads(data)
        change(index["config"])
        return json.dumps(index).encode()

    return _changed("data/weights/model_weights_config.json", edit)


def _description(change):
    def edit(data: bytes) -> bytes:
        meta = json.loads(data)
        change(meta)
        return json.dumps(meta).encode()

    return _changed("extra/mcrs.json", edit)


def _damaged(path: Path, member: str) -> None:
    """Flip one byte of ``member``'s data in the file itself, so that its CRC no longer matches."""
    with zipfile.ZipFile(path) as archive:
        info = next(i for i in archive.infolist() if i.filename.endswith(member))
    raw = bytearray(path.read_bytes())
    start = info.header_offset + 30 + len(info.filename.encode()) + len(info.extra)
    raw[start + 10] ^= 0xFF
    path.write_bytes(bytes(raw))


#: Cases that only mcrs's reading of the description catches (the program loader does not read it).
DESCRIPTION_ONLY = ("an int of 400 digits", "control characters in the name", "another hidden size",
                    "a hidden size of a billion", "a reversed action table")  # fmt: skip


#: (edit, what the refusal says): the tampered archives the tools meet, each refused before any episode.
TAMPERED = {
    "a compiled library": (_added(("data/aotinductor/model/model.so", b"ELF")), "unexpected archive member"),
    "a legacy pickled state": (_added(("data/weights/model.pt", b"x")), "unexpected archive member"),
    "a member given twice": (_added(("data/weights/weight_7", bytes(32))), "is there twice"),
    "a pickled weight": (
        _changed("data/weights/model_weights_config.json", lambda d: d.replace(b'"use_pickle": false', b'"use_pickle": true', 1)),
        "is not a plain float32 tensor",
    ),
    "a constant": (
        _changed("data/constants/model_constants_config.json", lambda d: b'{"config": {"c": {"path_name": "custom_obj_0"}}}'),
        "constant-free",
    ),
    "a truncated weight": (_changed("data/weights/weight_0", lambda d: d[:-4]), "is not a plain float32 tensor"),
    "a damaged member (CRC)": (_changed("data/weights/weight_0", lambda d: d), "cannot be read .Bad CRC"),
    "800 tensors over one member": (
        _weight_index(lambda c: c.update({f"agent.x{i}": c["agent.fc1.bias"] for i in range(800)})),
        r"not the agent's 8 tensors \(unexpected: \['agent.x0', 'agent.x1'\] ...",
    ),
    "two tensors over one member": (
        _weight_index(lambda c: c["agent.fc2.bias"].update(path_name=c["agent.fc1.bias"]["path_name"])),
        "is not a plain float32 tensor of its own",
    ),
    "20,000 dimensions": (
        _weight_index(lambda c: c["agent.fc1.bias"]["tensor_meta"].update(
            sizes=[{"as_int": 16}] + [{"as_int": 1}] * 20000, strides=[{"as_int": 1}] * 20001)),
        "is not a plain float32 tensor",
    ),
    "negative sizes": (
        _weight_index(lambda c: c["agent.fc1.bias"]["tensor_meta"].update(
            sizes=[{"as_int": -4}, {"as_int": -4}], strides=[{"as_int": -4}, {"as_int": 1}])),
        "is not a plain float32 tensor",
    ),
    "a description nested 100,000 deep": (_changed("extra/mcrs.json", lambda d: b"[" * 100_000), "nested too deep"),
    "a 2 MB description": (_changed("extra/mcrs.json", lambda d: d + b" " * (2 << 20)), "at most 1,048,576"),
    "an int of 400 digits": (_description(lambda m: m["env"].update(comm_range=10**400)), "lacks a usable env"),
    "control characters in the name": (
        _description(lambda m: m["env"].update(name="map10\n\x1b[1Aall good")), "not a printable name"),
    "another hidden size": (_description(lambda m: m["model"].update(hidden_dim=32)), "do not fit its description"),
    "a hidden size of a billion": (  # refused from the weights' shapes, before anything is allocated
        _description(lambda m: m["model"].update(hidden_dim=10**9)), "do not fit its description"),
    "a reversed action table": (_description(lambda m: m["moves"].reverse()), "has a wrong moves"),
}  # fmt: skip


@pytest.mark.parametrize("case", list(TAMPERED))
def test_a_tampered_export_is_refused_by_name_before_anything_runs(
    exported: Path, tmp_path: Path, case: str
) -> None:
    edit, message = TAMPERED[case]
    with warnings.catch_warnings():  # zipfile warns of the duplicate name it is asked to write
        warnings.simplefilter("ignore", UserWarning)
        crafted = _with_member(exported, tmp_path / "crafted.pt2", edit)
    if "CRC" in case:
        _damaged(crafted, "data/weights/weight_0")
    with pytest.raises(export.ExportError, match=message):
        export.exported_policy(crafted, scenario("map10"))
    if case not in DESCRIPTION_ONLY:
        with pytest.raises(export.ExportError, match=message):  # nor is the program loaded
            export.load_exported(crafted)


def test_the_weight_names_are_the_agents() -> None:
    from mcrs.models.agent import RecurrentAgent

    step = GreedyAgentStep(RecurrentAgent(5, 8, 2, 4))
    assert sorted(step.state_dict()) == sorted(export.AGENT_WEIGHTS)


def test_mcrs_render_draws_an_exported_agents_episode(exported: Path, tmp_path: Path) -> None:
    from mcrs.viz import write_episode_pictures

    paths = write_episode_pictures(tmp_path, scenario("map10", max_steps=5), str(exported), seed=0, gif=False)
    assert paths and all(p.is_file() for p in paths)
