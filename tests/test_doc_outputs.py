"""The outputs README.md and the docs quote are those of the commands they name.

A quoted output sits between two HTML comments (invisible on GitHub), the first naming the command::

    <!-- output of: mcrs-eval policy=all seed=1000000 episodes=32 figures=false -->
    ```
    | greedy    |   81.40 ± 9.33 | ...
    ```
    <!-- end output -->

Each command runs once, from an empty folder, and every line of each of its blocks must be a whole line
of what it printed (a ``<word>`` in the block stands for one path component or word, such as ``<run>``;
the folder's own path is cut from the output). ``slow output of:`` marks a command too long for the fast
suite (a training, a map20 evaluation), which then runs in the slow one."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ("README.md", "docs/TRAINING.md", "docs/API.md", "docs/EVALUATION.md")
BLOCK = re.compile(
    r"<!-- (?P<slow>slow )?output of: (?P<command>[^\n]*?) -->\n```[^\n]*\n(?P<body>.*?)```\n<!-- end output -->",
    re.S,
)
#: The console commands the blocks may name, as modules (pyproject.toml's [project.scripts]).
MODULES = {"mcrs-train": "mcrs.train", "mcrs-eval": "mcrs.evaluate"}
PLACEHOLDER = re.compile(r"<[\w ]+>")


def blocks() -> list[tuple[str, str, bool, list[str]]]:
    """``(document, command, slow, lines)`` of every quoted output in :data:`DOCS`."""
    found = []
    for doc in DOCS:
        for match in BLOCK.finditer((ROOT / doc).read_text()):
            lines = [line.rstrip() for line in match["body"].splitlines() if line.strip()]
            found.append((doc, match["command"], bool(match["slow"]), lines))
    return found


def commands() -> list:
    """One test per distinct command; slow when any of its blocks says so."""
    by_command: dict[str, bool] = {}
    for _, command, slow, _ in blocks():
        by_command[command] = by_command.get(command, False) or slow
    return [
        pytest.param(c, marks=[pytest.mark.slow] if slow else [], id=c[:80]) for c, slow in by_command.items()
    ]


def argv(command: str) -> list[str]:
    """The command as this interpreter runs it: ``mcrs-x`` as its module, ``python`` as ``sys.executable``,
    a repository file as its absolute path."""
    words = shlex.split(command)
    if words[0] in MODULES:
        head = [sys.executable, "-m", MODULES[words[0]]]
    elif words[0] == "python":
        head = [sys.executable]
    else:
        raise AssertionError(f"{command}: a block names an mcrs-train, mcrs-eval or python command")
    return head + [str(ROOT / w) if (ROOT / w).is_file() else w for w in words[1:]]


def output_of(command: str, folder: str) -> list[str]:
    env = {**os.environ, "HYDRA_FULL_ERROR": "0", "PYTHONPATH": str(ROOT)}
    done = subprocess.run(
        argv(command), cwd=folder, env=env, capture_output=True, text=True, timeout=1200, check=False
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return [line.rstrip() for line in done.stdout.replace(f"{folder}/", "").splitlines()]


def line_pattern(line: str) -> re.Pattern[str]:
    parts = PLACEHOLDER.split(line)
    return re.compile(r"[^\s/]+".join(re.escape(part) for part in parts))


def test_the_blocks_are_found_and_well_formed() -> None:
    found = blocks()
    assert {doc for doc, *_ in found} == set(DOCS)
    for doc, command, _, lines in found:
        assert lines, f"{doc}: the block of {command!r} quotes nothing"
        argv(command)
    for doc in DOCS:  # every opening comment has its block (a typo would leave one unchecked)
        text = (ROOT / doc).read_text()
        assert len(re.findall(r"^<!-- (?:slow )?output of: ", text, re.M)) == len(BLOCK.findall(text)), doc


@pytest.mark.parametrize("command", commands())
def test_a_quoted_output_is_what_its_command_prints(command: str, tmp_path_factory) -> None:
    folder = tmp_path_factory.mktemp("doc_output")
    printed = output_of(command, str(folder))
    for doc, quoted_command, _, lines in blocks():
        if quoted_command != command:
            continue
        for line in lines:
            pattern = line_pattern(line)
            assert any(pattern.fullmatch(out) for out in printed), (
                f"{doc}: {line!r} is not a line of what `{command}` printed:\n" + "\n".join(printed[-40:])
            )
