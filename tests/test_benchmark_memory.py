"""The episodic-memory benchmark runs end to end at a tiny size and prints every figure (no timing asserts)."""

from __future__ import annotations

import re

import pytest
import torch

from mcrs.benchmarks import memory as bench

NUMBER = r"([\d,]+(?:\.\d+)?)"
TINY = ["--entries", "3000", "--map", "map10", "--episodes", "2", "--lookups", "200", "--repeats", "1"]


def run(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    threads = torch.get_num_threads()
    assert bench.main(argv) == 0
    assert torch.get_num_threads() == threads  # restored
    return capsys.readouterr().out


def test_tiny_run_prints_every_figure(capsys: pytest.CaptureFixture[str]) -> None:
    out = run(capsys, [*TINY, "--threads", "1"])
    assert "command: mcrs-bench-memory --entries 3000 --map map10" in out
    assert "torch threads=1," in out and "load average" in out
    reembed = re.search(rf"^re-embed 3,000 states \(refresh_keys, chunks of 4096\): {NUMBER} s", out, re.M)
    insert = re.search(
        rf"^insert 100 transitions: {NUMBER} ms \(of which the CNN keys {NUMBER} ms\)", out, re.M
    )
    lookup = re.search(rf"^look-up 200 keys: {NUMBER} ms \({NUMBER} hits\)", out, re.M)
    ratio = re.search(
        rf"^reference \((?:scipy cKDTree|our grid index), one query per key in Python[^)]*\): build {NUMBER} s, "
        rf"queries {NUMBER} ms; "
        rf"ratio reference / ours = {NUMBER}x; same entries found: 200 of 200$",
        out,
        re.M,
    )
    size = re.search(rf"^buffer: {NUMBER} GiB held \(nbytes\); process resident memory growth", out, re.M)
    for match in (reembed, insert, lookup, ratio, size):
        assert match is not None, out
    assert float(insert.group(1)) > 0 and float(lookup.group(1)) > 0
    assert int(lookup.group(2)) >= 100  # the stored half of the keys are hits
    assert "goals: not judged" in out


def test_goal_lines_at_the_goal_sizes(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # Pretend the tiny sizes are the goal sizes, to check the verdict lines without a 1M buffer.
    for name, value in (
        ("GOAL_ENTRIES", 3000),
        ("GOAL_MAP", "map10"),
        ("GOAL_EPISODES", 2),
        ("GOAL_LOOKUPS", 200),
    ):
        monkeypatch.setattr(bench, name, value)
    out = run(capsys, ["--repeats", "1", "--threads", "1"])
    goals = out[out.index("goals:") :]
    for label in (
        "look-up of 200 keys at 1M entries <= 20 ms:",
        "insertion of 100 transitions <= 50 ms:",
        "re-embedding 1M map10 states (CNN) <= 10 s:",
        "buffer <= 1.5 GiB:",
        "look-up >= 20x the per-transition reference:",
    ):
        assert re.search(rf"^  {re.escape(label)} .* (PASS|FAIL)$", goals, re.M), goals


def test_without_scipy_the_reference_is_our_index_one_key_at_a_time(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import sys

    monkeypatch.setitem(sys.modules, "scipy.spatial", None)  # import fails
    out = run(capsys, [*TINY, "--threads", "1"])
    assert re.search(
        r"^reference \(our grid index, one query per key in Python \(scipy not installed\)\): .*"
        r"same entries found: 200 of 200$",
        out,
        re.M,
    ), out


def test_bad_sizes_are_refused(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        bench.main(["--entries", "0"])
    assert "--entries must be >= 1" in capsys.readouterr().err
