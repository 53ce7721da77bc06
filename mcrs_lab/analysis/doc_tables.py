"""``mcrs-results``: the tables and figures of docs/RESULTS.md, regenerated from the committed records.

    mcrs-results check            # exit 1 and a diff when a table (or figure) differs from the records'
    mcrs-results update           # rewrite those tables in place, and the figures' image files
    mcrs-results check docs/OTHER.md

With no document named, both act on docs/RESULTS.md and every notebook under results/notebooks/.

A generated table sits between two HTML comments (invisible on GitHub), the first naming the table file
and the ``mcrs-report`` command that writes it::

    <!-- table final.md of: mcrs-report results/records/baselines/campaign --env map20 -->
    | method | seeds | ... |
    <!-- end table -->

A generated figure is the same with ``figure`` and a PNG, around the image line; the image file (relative
to the document) is what the command draws::

    <!-- figure learning_curves.png of: mcrs-report results/records/baselines/campaign --env map20 -->
    ![learning curves, map20](results/map20_learning_curves.png)
    <!-- end figure -->

A figure whose records have not landed yet (a sweep not run, a map not trained) is not drawn by the
command; its block then says so, keeping the image line in a comment, and ``update`` draws it once they
have::

    <!-- figure delta.png of: mcrs-report results/records/paper/delta/campaign --env map20 -->
    *Not drawn yet: its records have not landed.* <!-- ![figure 11, map20](results/map20_delta.png) -->
    <!-- end figure -->

Each distinct command runs once, into a temporary folder, from the repository root (the folder holding
the document's ``docs/`` or ``results/notebooks/``), so the paths are the committed records'. A table or image outside these
blocks is not made from the records: ``check`` names its line and fails (``update`` leaves it alone).
"""

from __future__ import annotations

import argparse
import contextlib
import difflib
import io
import os
import re
import shlex
import sys
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from mcrs.experiment.util.atomic import ChangedSinceRead, write_bytes_atomic, write_if_unchanged
from mcrs.experiment.util.untrusted import UntrustedInput, confined
from mcrs_lab.analysis import report

BLOCK = re.compile(
    r"<!-- (?P<kind>table|figure) (?P<file>[\w.-]+\.(?:md|png)) of: mcrs-report (?P<args>[^\n]*?) -->\n"
    r"(?P<body>.*?)<!-- end (?P=kind) -->",
    re.S,
)
#: mcrs-report options that write files besides --out: refused in a document's blocks.
WRITING_OPTIONS = ("--out", "--marl-eval")
IMAGE = re.compile(r"!\[(?P<alt>[^\]]*)\]\((?P<path>[^)\s]+\.png)\)")
#: A figure block's body while its command draws nothing, around its image line.
NOT_DRAWN = "*Not drawn yet: its records have not landed.* <!-- {image} -->\n"


class DocTableError(Exception):
    """A generated table that cannot be made: its line and why."""


@dataclass(frozen=True)
class Block:
    """One generated table or figure of a document: where it is, what makes it, what the document holds
    now (a figure: its image line, whose file is ``image``)."""

    line: int
    file: str
    args: tuple[str, ...]
    body: str
    start: int  # offsets of ``body`` in the document
    end: int
    kind: str = "table"
    image: str = ""  # a figure's image path, relative to the document
    alt: str = ""  # a figure's image text

    def figure_body(self, drawn: bool) -> str:
        """What a figure block holds: its image line, or while nothing is drawn, :data:`NOT_DRAWN`."""
        line = f"![{self.alt}]({self.image})"
        return f"{line}\n" if drawn else NOT_DRAWN.format(image=line)


def _writes(option: str) -> bool:
    """``option`` is one of :data:`WRITING_OPTIONS` or an abbreviation argparse would accept for it."""
    return len(option) > 2 and option.startswith("--") and any(w.startswith(option) for w in WRITING_OPTIONS)


def find_blocks(text: str) -> list[Block]:
    """The generated tables and figures of ``text``, in order. Refuses a ``--out`` (the tool chooses the folder)."""
    blocks = []
    for match in BLOCK.finditer(text):
        line = text.count("\n", 0, match.start()) + 1
        try:
            args = tuple(shlex.split(match["args"]))
        except ValueError as error:
            raise DocTableError(f"line {line}: the mcrs-report command cannot be read: {error}") from None
        if "--out" in args:
            raise DocTableError(
                f"line {line}: leave --out out of the command; the table is made in a temporary folder"
            )
        written = [a for a in args if _writes(a.split("=", 1)[0])]
        if written:  # a document must not make the tool write a file of its choosing
            raise DocTableError(
                f"line {line}: {written[0].split('=', 1)[0]} writes a file: a generated block may not use it "
                f"(allowed options: --env, --claims, --tsne, --tsne-samples, --seed)"
            )
        if (match["kind"] == "table") != match["file"].endswith(".md"):
            raise DocTableError(f"line {line}: a table is a .md file and a figure a .png: {match['file']}")
        image = IMAGE.search(match["body"]) if match["kind"] == "figure" else None
        if match["kind"] == "figure" and image is None:
            raise DocTableError(f"line {line}: a figure block needs an image line ![...](<path>.png)")
        blocks.append(
            Block(
                line,
                match["file"],
                args,
                match["body"],
                match.start("body"),
                match.end("body"),
                match["kind"],
                image["path"] if image else "",
                image["alt"] if image else "",
            )
        )
    return blocks


def _root(doc: Path) -> Path:
    """The folder the commands run in: the repository root for a document under ``docs/`` or
    ``results/notebooks/``, else the document's own folder."""
    folder = doc.resolve().parent
    if folder.name == "docs":
        return folder.parent
    if folder.name == "notebooks" and folder.parent.name == "results":
        return folder.parent.parent
    return folder


@contextlib.contextmanager
def _inside(folder: Path) -> Iterator[None]:
    """Run in ``folder`` and come back (``contextlib.chdir`` is Python 3.11+)."""
    before = Path.cwd()
    os.chdir(folder)
    try:
        yield
    finally:
        os.chdir(before)


def generate(blocks: list[Block], root: Path) -> dict[Block, str | bytes | None]:
    """Each table as ``mcrs-report`` writes it now, and each figure's PNG bytes, or None for a figure of
    :data:`report.FIGURES` that the records do not draw yet (each distinct command runs once, quietly)."""
    made: dict[tuple[str, ...], Path] = {}
    out: dict[Block, str | bytes | None] = {}
    with tempfile.TemporaryDirectory(prefix="mcrs-results-") as tmp, _inside(root):
        for block in blocks:
            if block.args not in made:
                folder = Path(tmp) / str(len(made))
                try:
                    with contextlib.redirect_stdout(io.StringIO()):
                        report.main([*block.args, "--out", str(folder)])
                except SystemExit as error:
                    raise DocTableError(
                        f"line {block.line}: mcrs-report {shlex.join(block.args)}: {error}"
                    ) from None
                made[block.args] = folder
            path = made[block.args] / block.file
            if not path.is_file() and block.kind == "figure" and block.file in report.FIGURES:
                out[block] = None
                continue
            if not path.is_file():
                suffix = Path(block.file).suffix
                written = sorted(p.name for p in made[block.args].glob(f"*{suffix}") if p.name != "report.md")
                raise DocTableError(
                    f"line {block.line}: mcrs-report {shlex.join(block.args)} writes no {block.file}; "
                    f"it writes: {', '.join(written) or 'no ' + block.kind}"
                )
            out[block] = path.read_bytes() if block.kind == "figure" else path.read_text()
    return out


def hand_made(text: str) -> list[int]:
    """The lines of tables and images outside the generated blocks (the first line of each table)."""
    lines = []
    blocks = [(m.start(), m.end()) for m in BLOCK.finditer(text)]
    offset, previous = 0, ""
    for number, line in enumerate(text.splitlines(keepends=True), start=1):
        inside = any(start <= offset < end for start, end in blocks)
        starts_table = line.startswith("|") and not previous.startswith("|")
        if not inside and (starts_table or IMAGE.search(line)):
            lines.append(number)
        offset, previous = offset + len(line), line
    return lines


def check(doc: Path) -> list[str]:
    """A unified diff per table of ``doc`` that differs from what the records give, and a line per table
    or image not made from them (empty: all agree)."""
    text = doc.read_text()
    diffs = [
        f"{doc}:{line}: a table or figure outside the generated blocks: not made from the records\n"
        for line in hand_made(text)
    ]
    for block, fresh in generate(find_blocks(text), _root(doc)).items():
        if block.kind == "figure":
            command = f"mcrs-report {shlex.join(block.args)}"
            if fresh is None and block.body != block.figure_body(drawn=False):
                diffs.append(
                    f"{doc}:{block.line}: figure {block.image}: {command} draws no {block.file} now\n"
                )
            if isinstance(fresh, bytes) and block.body != block.figure_body(drawn=True):
                diffs.append(f"{doc}:{block.line}: figure {block.image} is drawn now by {command}\n")
            image = _image_path(doc, block)
            if isinstance(fresh, bytes) and (not image.is_file() or image.read_bytes() != fresh):
                state = "differs from" if image.is_file() else "is missing; it should be"
                diffs.append(
                    f"{doc}:{block.line}: figure {block.image} {state} the {block.file} of {command}\n"
                )
            continue
        if fresh != block.body:
            lines = difflib.unified_diff(
                block.body.splitlines(keepends=True),
                fresh.splitlines(keepends=True),
                f"{doc}:{block.line} ({block.file}, as committed)",
                f"mcrs-report {shlex.join(block.args)}",
            )
            diffs.append("".join(lines))
    return diffs


def _image_path(doc: Path, block: Block) -> Path:
    """A figure's image file, which must lie inside the repository (the folder the commands run in)."""
    try:
        return confined(doc.parent / block.image, _root(doc), f"line {block.line}: the image")
    except UntrustedInput as error:
        raise DocTableError(str(error)) from None


def update(doc: Path) -> int:
    """Rewrite every generated table of ``doc``, and every generated figure's image, from the records
    (each file atomically, and nothing when one cannot be made); how many changed. The document is
    replaced only if it is as it was read (:func:`write_if_unchanged`): an edit made while the tables were
    generated is kept and the update refused."""
    read = doc.read_bytes()
    text = read.decode()
    blocks = find_blocks(text)
    fresh = generate(blocks, _root(doc))  # a minute or more: the document may be edited meanwhile
    if doc.read_bytes() != read:  # before any image: an update refused writes nothing
        raise ChangedSinceRead(
            f"{doc} changed since it was read: nothing written (the change is kept); run again"
        )
    changed = 0
    for block in reversed(blocks):  # from the end, so the earlier offsets stay valid
        made = fresh[block]
        if block.kind == "figure":
            image = _image_path(doc, block)
            if isinstance(made, bytes) and (not image.is_file() or image.read_bytes() != made):
                write_bytes_atomic(image, made)  # drawn from the records alone
                changed += 1
            body = block.figure_body(drawn=made is not None)
            if body != block.body:
                text = text[: block.start] + body + text[block.end :]
                changed += 1
        elif made != block.body:
            text = text[: block.start] + made + text[block.end :]
            changed += 1
    if text.encode() != read:
        write_if_unchanged(doc, text.encode(), read)
    return changed


#: The documents ``mcrs-results`` checks when none is named: the answer sheet and the notebooks that keep
#: the campaigns' histories.
DEFAULT_DOCS = (Path("docs/RESULTS.md"), Path("results/notebooks"))


def default_docs() -> list[Path]:
    """docs/RESULTS.md and every notebook under results/notebooks/, in name order."""
    answer, notebooks = DEFAULT_DOCS
    return [answer, *sorted(notebooks.glob("*.md"))]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mcrs-results",
        description="Check or rewrite the generated tables of results documents from the committed records.",
    )
    parser.add_argument("action", choices=["check", "update"])
    parser.add_argument(
        "docs",
        nargs="*",
        type=Path,
        help="default: docs/RESULTS.md and results/notebooks/*.md",
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    status = 0
    for doc in args.docs or default_docs():
        status = max(status, _run(args.action, doc))
    return status


def _run(action: str, doc: Path) -> int:
    """``action`` on one document; 0 when it agrees with the records (or was rewritten), else 1."""
    try:
        text = doc.read_text()
        n, hand = len(find_blocks(text)), len(hand_made(text))
        if action == "update":
            print(f"{doc}: {update(doc)} of {n} generated tables and figures rewritten")
            return 0
        diffs = check(doc)
    except ChangedSinceRead as error:
        raise SystemExit(f"mcrs-results: error: {error}") from None
    except (DocTableError, OSError, UnicodeDecodeError) as error:
        raise SystemExit(f"mcrs-results: error: {doc}: {error}") from None
    if diffs:
        print("\n".join(diffs))
        if len(diffs) > hand:
            print(
                f"{doc}: {len(diffs) - hand} of {n} generated tables and figures differ from the records (mcrs-results update)"
            )
        if hand:
            print(f"{doc}: {hand} tables or figures are not generated from the records (make them blocks)")
        return 1
    waiting = sum(b.kind == "figure" and b.body == b.figure_body(drawn=False) for b in find_blocks(text))
    print(
        f"{doc}: all {n} generated tables and figures agree with the records"
        + (f" ({waiting} figure{'s' * (waiting > 1)} not drawn yet, awaiting records)" if waiting else "")
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
