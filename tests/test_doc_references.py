"""The Python names and repository paths that README.md and docs/*.md quote in code resolve today.

A doc that sends a reader to ``mcrs.env.ScenarioConfig`` or ``mcrs/memory/index.py`` after the name moved
is wrong in a way no reader can repair. A dotted name passes when it imports (a module, then attributes),
or when the package spells it as a string (a logger, an entry-point group, a resolver, a file inside an
archive); a path passes when the file or folder exists (a pattern, when something matches it)."""

from __future__ import annotations

import importlib
import re
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
PACKAGES = ("mcrs", "mcrs_lab", "benchmarks")

#: Inline code and fenced blocks: prose may say "mcrs" as a word, code quotes a name.
CODE = re.compile(r"```.*?```|`[^`\n]+`", re.S)
DOTTED = re.compile(r"(?<![\w/.-])((?:mcrs|mcrs_lab|mcrs_benchmarks)(?:\.[A-Za-z_]\w*)+)")
PATH = re.compile(r"(?<![\w/.-])((?:mcrs|mcrs_lab|benchmarks)/[\w./*<>-]*[\w*>])")
#: A placeholder in a quoted path, as ``<group>`` in ``mcrs/conf/<group>/``: any one name.
PLACEHOLDER = re.compile(r"<[^<>/]*>")


def quoted(pattern: re.Pattern[str]) -> list[tuple[str, str]]:
    """Each (doc, name) the pattern finds inside the docs' code, once."""
    found = {
        (doc.relative_to(ROOT).as_posix(), name)
        for doc in DOCS
        for span in CODE.findall(doc.read_text())
        for name in pattern.findall(span)
    }
    return sorted(found)


def resolve(dotted: str) -> Any:
    """The object a dotted name names: its longest importable module prefix, then attributes."""
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            found: Any = importlib.import_module(".".join(parts[:cut]))
        except ModuleNotFoundError:
            continue
        for attribute in parts[cut:]:
            found = getattr(found, attribute)
        return found
    raise ModuleNotFoundError(dotted)


def spelled_in_the_package(name: str) -> bool:
    """Whether some module of the package has ``name`` as a string literal."""
    literal = (f'"{name}"', f"'{name}'")
    return any(
        any(text in source.read_text() for text in literal)
        for package in PACKAGES
        for source in (ROOT / package).rglob("*.py")
    )


@pytest.mark.parametrize(("doc", "name"), quoted(DOTTED))
def test_a_python_name_quoted_in_the_docs_exists(doc: str, name: str) -> None:
    try:
        resolve(name)
    except (ImportError, AttributeError) as error:
        assert spelled_in_the_package(name), f"{doc} quotes `{name}`, which names nothing: {error}"


@pytest.mark.parametrize(("doc", "path"), quoted(PATH))
def test_a_repository_path_quoted_in_the_docs_exists(doc: str, path: str) -> None:
    pattern = PLACEHOLDER.sub("*", path)
    assert any(ROOT.glob(pattern)), f"{doc} quotes `{path}`, which is not in the repository"


def test_the_docs_quote_names_and_paths_to_check() -> None:
    assert len(quoted(DOTTED)) > 30 and len(quoted(PATH)) > 30  # the patterns still find the docs' code


def test_a_moved_name_is_caught() -> None:
    with pytest.raises(AttributeError):
        resolve("mcrs.env.NoSuchConfig")
    assert not spelled_in_the_package("mcrs.no_such_logger")
    assert spelled_in_the_package("mcrs.pid")  # a Hydra resolver, quoted as `${mcrs.pid:}`
