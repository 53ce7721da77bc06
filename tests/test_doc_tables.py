"""``mcrs-results``: the generated tables of a results document are what ``mcrs-report`` makes of the
committed records, checked and rewritten in place; docs/RESULTS.md itself agrees with the records."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from mcrs_lab.analysis.doc_tables import DocTableError, _root, check, default_docs, find_blocks, main, update

RECORDS = Path(
    "results/records/near/heuristics/map20"
)  # three greedy/lawnmower/random evaluations, committed
COMMAND = f"mcrs-report {RECORDS} --env map20"


def _repo(
    tmp_path: Path, body: str = "| stale |\n", file: str = "evaluations.md", command: str = COMMAND
) -> Path:
    """A copy of the heuristic records and a document under docs/ with one generated table."""
    shutil.copytree(RECORDS, tmp_path / RECORDS)
    doc = tmp_path / "docs" / "R.md"
    doc.parent.mkdir()
    doc.write_text(
        f"# R\n\nbefore\n\n<!-- table {file} of: {command} -->\n{body}<!-- end table -->\n\nafter\n"
    )
    return doc


def test_update_writes_the_records_table_and_check_then_agrees(tmp_path: Path) -> None:
    doc = _repo(tmp_path)
    assert check(doc)  # the stale body differs
    assert update(doc) == 1
    text = doc.read_text()
    (table,) = find_blocks(text)
    assert "| greedy (heuristic)" in table.body and "306.61 ± 2.00" in table.body
    assert text.startswith("# R\n\nbefore\n\n<!-- table evaluations.md") and text.endswith(
        "<!-- end table -->\n\nafter\n"
    )
    assert check(doc) == [] and update(doc) == 0


def test_check_names_the_line_and_shows_the_changed_number(tmp_path: Path, capsys) -> None:
    doc = _repo(tmp_path)
    update(doc)
    doc.write_text(doc.read_text().replace("306.61", "399.99"))
    (diff,) = check(doc)
    assert f"{doc}:5 (evaluations.md, as committed)" in diff
    assert "-| greedy (heuristic)" in diff and "399.99" in diff and "+| greedy (heuristic)" in diff
    assert main(["check", str(doc)]) == 1
    assert "1 of 1 generated tables and figures differ" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("file", "command", "says"),
    [
        ("evaluations.md", f"{COMMAND} --out x", "leave --out out"),
        ("final.md", COMMAND, "writes no final.md; it writes: evaluations.md"),
        ("evaluations.md", "mcrs-report results/none --env map20", "no readable runs"),
    ],
)
def test_a_table_that_cannot_be_made_is_one_line_and_the_document_is_untouched(
    tmp_path: Path, file: str, command: str, says: str
) -> None:
    doc = _repo(tmp_path, file=file, command=command)
    before = doc.read_text()
    with pytest.raises(DocTableError, match=f"line 5: .*{says}"):
        update(doc)
    assert doc.read_text() == before
    with pytest.raises(SystemExit, match=f"mcrs-results: error: .*{says}"):
        main(["update", str(doc)])


def test_a_hand_made_table_or_image_fails_the_check(tmp_path: Path, capsys) -> None:
    doc = _repo(tmp_path)
    update(doc)
    assert check(doc) == []
    lines = len(doc.read_text().splitlines())  # the hand-made table starts 2 lines on, the image 6
    doc.write_text(doc.read_text() + "\n| a | b |\n|---|---|\n| 1 | 2 |\n\n![old](results/old.png)\n")
    assert [d.split(": a table")[0] for d in check(doc)] == [f"{doc}:{lines + 2}", f"{doc}:{lines + 6}"]
    assert main(["check", str(doc)]) == 1
    out = capsys.readouterr().out
    assert "2 tables or figures are not generated" in out and "differ from the records" not in out


RANGES = Path("results/records/near/comm_range/map20")  # greedy at R_c 0..10, 3 evaluation seeds, committed


def test_a_generated_figure_is_drawn_from_the_records_and_checked(tmp_path: Path, capsys) -> None:
    shutil.copytree(RANGES, tmp_path / RANGES)
    doc = tmp_path / "docs" / "R.md"
    doc.parent.mkdir()
    text = (
        f"# R\n\n<!-- figure comm_range.png of: mcrs-report {RANGES} --env map20 -->\n"
        "![R_c](results/rc.png)\n<!-- end figure -->\n"
    )
    doc.write_text(text)
    image = doc.parent / "results" / "rc.png"
    (diff,) = check(doc)
    assert "figure results/rc.png is missing" in diff
    assert update(doc) == 1
    assert image.read_bytes().startswith(b"\x89PNG") and doc.read_text() == text  # the text stays
    assert check(doc) == [] and update(doc) == 0  # drawn again, the same bytes
    image.write_bytes(image.read_bytes()[:-10])
    assert main(["check", str(doc)]) == 1
    assert "figure results/rc.png differs from the comm_range.png" in capsys.readouterr().out
    doc.write_text(text.replace("![R_c](results/rc.png)", "no image here"))
    with pytest.raises(DocTableError, match=r"line 3: a figure block needs an image line"):
        update(doc)


def test_a_figure_whose_records_have_not_landed_says_so_until_they_draw_it(tmp_path: Path, capsys) -> None:
    """A block may name a figure its records do not draw yet: it says so and is drawn once they land."""
    shutil.copytree(RECORDS, tmp_path / RECORDS)  # heuristics at one R_c: no figure of R_c yet
    doc = tmp_path / "docs" / "R.md"
    doc.parent.mkdir()
    header = f"<!-- figure comm_range.png of: {COMMAND.replace(' --env', f' {RANGES} --env')} -->\n"
    not_drawn = "*Not drawn yet: its records have not landed.* <!-- ![R_c](results/rc.png) -->\n"
    doc.write_text(f"# R\n\n{header}{not_drawn}<!-- end figure -->\n")
    image = doc.parent / "results" / "rc.png"
    assert check(doc) == [] and update(doc) == 0 and not image.exists()
    assert main(["check", str(doc)]) == 0
    assert (
        "all 1 generated tables and figures agree with the records (1 figure not drawn yet, awaiting records)"
        in (capsys.readouterr().out)
    )
    doc.write_text(doc.read_text().replace(not_drawn, "![R_c](results/rc.png)\n"))  # claims it is drawn
    (diff,) = check(doc)
    assert diff.endswith(
        f"{doc}:3: figure results/rc.png: mcrs-report {RECORDS} {RANGES} --env map20 draws no comm_range.png now\n"
    )
    assert update(doc) == 1 and not_drawn in doc.read_text() and not image.exists()
    shutil.copytree(RANGES, tmp_path / RANGES)  # the ranges land
    assert [d.split(": figure ")[1].split(" ")[1:3] for d in check(doc)] == [
        ["is", "drawn"],
        ["is", "missing;"],
    ]
    assert update(doc) == 2 and image.read_bytes().startswith(b"\x89PNG")
    assert "![R_c](results/rc.png)\n<!-- end figure -->" in doc.read_text() and check(doc) == []
    doc.write_text(doc.read_text().replace("comm_range.png of", "ranges.png of"))  # no such figure
    with pytest.raises(DocTableError, match=r"line 3: .* writes no ranges.png; it writes: comm_range.png"):
        check(doc)
    with pytest.raises(SystemExit, match=r"mcrs-results: error: .* writes no ranges.png"):
        main(["check", str(doc)])


def test_the_checked_documents_are_the_answer_sheet_and_its_notebooks() -> None:
    docs = default_docs()
    assert docs[0] == Path("docs/RESULTS.md") and len(docs) >= 6
    assert len(find_blocks(docs[0].read_text())) >= 5


@pytest.mark.slow
@pytest.mark.parametrize("doc", default_docs(), ids=str)
def test_results_md_agrees_with_the_committed_records(doc: Path) -> None:
    """Every generated table and figure of docs/RESULTS.md and of each notebook is what mcrs-report makes
    of the committed records alone (no run directories); one document a test, so they check side by side."""
    assert check(doc) == [], doc


def test_a_notebook_runs_its_commands_from_the_repository_root(tmp_path: Path, capsys) -> None:
    """A notebook under results/notebooks/ names records from the repository root, as docs/ does; with no
    document named, mcrs-results checks the answer sheet and every notebook."""
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "RESULTS.md").write_text("no tables\n")
    notebooks = tmp_path / "results" / "notebooks"
    notebooks.mkdir(parents=True)
    (notebooks / "b.md").write_text("| a | b |\n|---|---|\n| 1 | 2 |\n")  # a table not made from records
    (notebooks / "a.md").write_text("prose only\n")
    before = Path.cwd()
    os.chdir(tmp_path)
    try:
        assert default_docs() == [
            Path("docs/RESULTS.md"),
            notebooks.relative_to(tmp_path) / "a.md",
            notebooks.relative_to(tmp_path) / "b.md",
        ]
        assert main(["check"]) == 1
    finally:
        os.chdir(before)
    out = capsys.readouterr().out
    assert "docs/RESULTS.md: all 0 generated tables and figures agree" in out
    assert "results/notebooks/b.md: 1 tables or figures are not generated from the records" in out
    assert _root(notebooks / "b.md") == tmp_path.resolve()


def test_a_missing_document_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match=r"^mcrs-results: error: .*nope\.md: .*No such file"):
        main(["check", str(tmp_path / "nope.md")])
