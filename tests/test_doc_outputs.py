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
suite (a training, a map20 evaluation), which then runs in the slow one.

A trained policy's figures depend on the CPU's floating-point path: torch and MKL pick their kernels by
the CPU (its vendor and its vector instructions), so a training rounds differently and, thousands of
updates later, lands elsewhere, while the heuristics' figures stay the same. A block that quotes a
training names the CPU kind its numbers were printed on (``<!-- slow output of: CMD | cpu: AMD AVX2 -->``):
on that kind every number must match; on another each decimal number of the block stands for any number
with as many decimals, and the rest of every line must still match.
"""

from __future__ import annotations

import os
import platform
import re
import shlex
import subprocess
import sys
from pathlib import Path
from typing import NamedTuple

import pytest

from mcrs_lab.analysis.records import cpuinfo

ROOT = Path(__file__).resolve().parents[1]
DOCS = ("README.md", "docs/TRAINING.md", "docs/API.md", "docs/EVALUATION.md")
BLOCK = re.compile(
    r"<!-- (?P<slow>slow )?output of: (?P<command>[^\n]*?)(?: \| cpu: (?P<cpu>[^\n]*?))? -->\n"
    r"```[^\n]*\n(?P<body>.*?)```\n<!-- end output -->",
    re.S,
)
#: The console commands the blocks may name, as modules (pyproject.toml's [project.scripts]).
MODULES = {"mcrs-train": "mcrs.train", "mcrs-eval": "mcrs.evaluate"}
PLACEHOLDER = re.compile(r"<[\w ]+>")
#: A decimal number standing alone (not part of a word such as ``map10`` or ``32k``); group 1: its decimals.
DECIMAL = re.compile(r"(?<![\w.])\d+\.(\d+)(?![\w.])")
#: /proc/cpuinfo's vendor_id as a block names it.
VENDORS = {"AuthenticAMD": "AMD", "GenuineIntel": "Intel"}


class Block(NamedTuple):
    doc: str
    command: str
    slow: bool
    cpu: str | None  # the CPU kind its numbers were printed on; None: the same numbers on every CPU
    lines: list[str]


def this_cpu() -> str:
    """This machine's CPU kind as the blocks name it: the vendor and torch's kernel capability."""
    import torch

    vendor = cpuinfo("vendor_id")
    return f"{VENDORS.get(vendor, vendor) if vendor else platform.machine()} {torch.backends.cpu.get_cpu_capability()}"


def blocks() -> list[Block]:
    """Every quoted output in :data:`DOCS`."""
    found = []
    for doc in DOCS:
        for match in BLOCK.finditer((ROOT / doc).read_text()):
            lines = [line.rstrip() for line in match["body"].splitlines() if line.strip()]
            found.append(Block(doc, match["command"], bool(match["slow"]), match["cpu"], lines))
    return found


def commands() -> list:
    """One test per distinct command; slow when any of its blocks says so."""
    by_command: dict[str, bool] = {}
    for block in blocks():
        by_command[block.command] = by_command.get(block.command, False) or block.slow
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


def line_pattern(line: str, any_decimals: bool = False) -> re.Pattern[str]:
    """The printed lines that ``line`` quotes: each ``<word>`` is one path component or word; with
    ``any_decimals``, each decimal number is any number with as many decimals."""

    def literal(text: str) -> str:
        if not any_decimals:
            return re.escape(text)
        pieces = DECIMAL.split(text)  # text, decimals, text, decimals, ..., text
        return "".join(
            re.escape(piece) if i % 2 == 0 else rf"\d+\.\d{{{len(piece)}}}" for i, piece in enumerate(pieces)
        )

    return re.compile(r"[^\s/]+".join(literal(part) for part in PLACEHOLDER.split(line)))


def test_the_blocks_are_found_and_well_formed() -> None:
    found = blocks()
    assert {block.doc for block in found} == set(DOCS)
    for block in found:
        assert block.lines, f"{block.doc}: the block of {block.command!r} quotes nothing"
        argv(block.command)
        assert block.cpu is None or re.fullmatch(r"(AMD|Intel|\S+) \S+", block.cpu), (
            f"{block.doc}: the block of {block.command!r}: cpu: {block.cpu!r} is not '<vendor> <capability>'"
        )
    for doc in DOCS:  # every opening comment has its block (a typo would leave one unchecked)
        text = (ROOT / doc).read_text()
        assert len(re.findall(r"^<!-- (?:slow )?output of: ", text, re.M)) == len(BLOCK.findall(text)), doc


@pytest.mark.parametrize("command", commands())
def test_a_quoted_output_is_what_its_command_prints(command: str, tmp_path_factory) -> None:
    folder = tmp_path_factory.mktemp("doc_output")
    printed = output_of(command, str(folder))
    cpu = this_cpu()
    for block in blocks():
        if block.command != command:
            continue
        other_cpu = block.cpu is not None and block.cpu != cpu
        where = f" (its numbers are a {block.cpu} CPU's; this one is {cpu})" if other_cpu else ""
        for line in block.lines:
            pattern = line_pattern(line, any_decimals=other_cpu)
            assert any(pattern.fullmatch(out) for out in printed), (
                f"{block.doc}: {line!r} is not a line of what `{command}` printed{where}:\n"
                + "\n".join(printed[-40:])
            )


def test_on_another_cpu_a_line_keeps_every_word_and_each_numbers_decimals() -> None:
    quoted = "report (map10, episode reward: cnn_semu (32k steps) 85.3, greedy (heuristic) 81.40):"
    printed = "report (map10, episode reward: cnn_semu (32k steps) 84.9, greedy (heuristic) 80.25):"
    assert line_pattern(quoted).fullmatch(quoted)
    assert not line_pattern(quoted).fullmatch(printed)
    assert line_pattern(quoted, any_decimals=True).fullmatch(printed)
    for changed in (
        printed.replace("map10", "map15"),
        printed.replace("32k", "64k"),
        printed.replace("84.9,", "84.91,"),
        printed.replace("cnn_semu", "qmix"),
        printed.replace("80.25", "n/a"),
    ):
        assert not line_pattern(quoted, any_decimals=True).fullmatch(changed), changed


def test_this_cpu_is_named_as_the_blocks_name_it() -> None:
    import torch

    vendor, capability = this_cpu().split(" ")
    assert capability == torch.backends.cpu.get_cpu_capability()
    assert vendor not in VENDORS  # the short name, never /proc/cpuinfo's vendor_id
