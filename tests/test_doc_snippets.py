"""The code blocks of README.md and the first docs a user reads run as a user would copy them: each Python
block alone, in a fresh interpreter and an empty folder (a block marked as a fragment of a program names
the file that holds it whole); each ``mcrs-train``, ``mcrs-eval`` and
``mcrs-render`` line of a shell block composes and passes the checks made before anything runs; each
``mcrs-campaign``, ``mcrs-report`` and ``mcrs-results`` line parses, and its campaign file and filters load.

A Python block that trains is in the slow set, with its budget cut to a few thousand env steps where it
asks for more (the page's figures are kept by tests/test_doc_outputs.py). A ``<run>`` in a command
stands for a run directory; the commands themselves are not run here (their budgets are hours)."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import open_dict

from mcrs.experiment.schema import CONFIG_DIR

ROOT = Path(__file__).resolve().parents[1]
DOCS = ("README.md", "docs/TRAINING.md", "docs/API.md", "docs/EVALUATION.md")
FENCE = re.compile(
    r"^(?:<!-- fragment: [^\n]*? whole in (?P<whole>\S+) -->\n)?```(?P<lang>python|bash)\n(?P<body>.*?)^```",
    re.S | re.M,
)
#: The pages whose shell blocks run the lab's tools (mcrs-campaign, mcrs-report, mcrs-results).
LAB_DOCS = ("README.md", "docs/EXPERIMENTS.md")
LAB_TOOLS = ("mcrs-campaign", "mcrs-report", "mcrs-results")
#: The Hydra config each command composes.
CONFIGS = {"mcrs-train": "config", "mcrs-eval": "eval", "mcrs-render": "render"}
#: A budget above this many env steps is cut to it (a block's own figures are kept elsewhere).
MAX_STEPS = 3200
STEPS = re.compile(r"train\.total_env_steps=(\d+)")


def snippets(lang: str, fragments: bool = False, docs: tuple[str, ...] = DOCS) -> list[tuple[str, str]]:
    """``(doc:line, body)`` of each block in ``lang``: the whole programs, or (``fragments``) the blocks
    marked ``<!-- fragment: ... whole in <file> -->``, which use names of the reader's own code, as
    ``(doc:line, file)``."""
    found = []
    for doc in docs:
        text = (ROOT / doc).read_text()
        for match in FENCE.finditer(text):
            if match["lang"] == lang and bool(match["whole"]) == fragments:
                line = text[: match.start()].count("\n") + 1
                found.append((f"{doc}:{line}", match["whole"] or match["body"]))
    return found


def python_params() -> list:
    params = []
    for where, body in snippets("python"):
        slow = any(call in body for call in ("Experiment(", "export_agent(", "rollout("))
        params.append(pytest.param(body, marks=[pytest.mark.slow] if slow else [], id=where))
    return params


def command_lines(tools: tuple[str, ...] = tuple(CONFIGS), docs: tuple[str, ...] = DOCS) -> list:
    params = []
    for where, body in snippets("bash", docs=docs):
        for offset, line in enumerate(body.splitlines()):
            words = shlex.split(line, comments=True)
            if words and words[0] in tools:
                doc, start = where.split(":")
                params.append(pytest.param(words, id=f"{doc}:{int(start) + 1 + offset}"))
    return params


def tiny(body: str) -> str:
    """``body`` with every training budget above :data:`MAX_STEPS` cut to it."""
    return STEPS.sub(lambda m: f"train.total_env_steps={min(int(m[1]), MAX_STEPS)}", body)


@pytest.mark.parametrize("body", python_params())
def test_a_python_block_runs_copied_alone(body: str, tmp_path: Path) -> None:
    (tmp_path / "snippet.py").write_text(tiny(body))
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg"}
    done = subprocess.run(
        [sys.executable, "snippet.py"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900
    )
    assert done.returncode == 0, done.stderr[-3000:]


@pytest.mark.parametrize("words", command_lines())
def test_a_documented_command_composes_and_passes_the_early_checks(words: list[str], tmp_path: Path) -> None:
    # the three commands' schemas, registered on import
    import mcrs.evaluate
    import mcrs.render_episode
    import mcrs.train  # noqa: F401
    from mcrs.experiment.run.rundir import register_resolvers

    register_resolvers()
    run = tmp_path / "run"
    overrides = [w.replace("outputs/map10/qmix/<run>", str(run)).replace("<run>", "run") for w in words[1:]]
    if "-m" in overrides:  # a sweep: its first job
        overrides = [o.split(",")[0] if "=" in o and "[" not in o else o for o in overrides if o != "-m"]
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base=None):
        cfg = compose(CONFIGS[words[0]], overrides=overrides, return_hydra_config=True)
    with open_dict(cfg):  # composed (Hydra's own keys checked); the checks read the rest
        del cfg["hydra"]
    if words[0] == "mcrs-train":
        from mcrs.train import early_errors

        assert early_errors(cfg, overrides) == []
    elif words[0] == "mcrs-eval":
        from mcrs.evaluate import eval_errors

        assert eval_errors(cfg) == []


@pytest.mark.parametrize("words", command_lines(LAB_TOOLS, LAB_DOCS))
def test_a_documented_lab_command_parses_and_its_campaign_file_loads(words: list[str]) -> None:
    """A flag renamed or dropped, a campaign file moved, an ``--only`` that selects nothing: the line a
    reader copies would fail. The commands are not run (a campaign takes days)."""
    from mcrs_lab.analysis.doc_tables import build_parser as results_parser
    from mcrs_lab.analysis.report import build_parser as report_parser
    from mcrs_lab.campaign.cli import build_parser as campaign_parser
    from mcrs_lab.campaign.matrix import campaign_roots, load_matrix, select

    parsers = {"mcrs-campaign": campaign_parser, "mcrs-report": report_parser, "mcrs-results": results_parser}
    args = [w.replace("<run dir>", "outputs/run") for w in words[1:] if w != "..."]
    parsed = parsers[words[0]]().parse_args(args)
    if words[0] == "mcrs-campaign" and getattr(parsed, "matrix", None) is not None:
        matrix = parsed.matrix if parsed.matrix.is_absolute() else ROOT / parsed.matrix
        campaign_roots(matrix)
        points, _ = load_matrix(matrix)
        assert select(points, getattr(parsed, "only", [])), f"{' '.join(words)}: --only selects no point"


def test_the_pages_have_blocks() -> None:
    assert len(snippets("python")) >= 10 and len(command_lines()) >= 30
    assert len(command_lines(LAB_TOOLS, LAB_DOCS)) >= 10


def test_a_fragment_names_the_file_that_runs_it_whole() -> None:
    """A block of a program's parts (``qnet``, ``batch`` are the reader's) says where the whole program
    is, and that file is in the repository (its own test runs it)."""
    fragments = snippets("python", fragments=True)
    assert fragments
    for where, whole in fragments:
        assert (ROOT / whole).is_file(), f"{where}: {whole} is not in the repository"
