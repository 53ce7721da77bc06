"""The episodic-memory benchmark runs end to end at a tiny size, prints every figure and writes them as JSON
(no timing asserts)."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest
import torch
from mcrs_benchmarks import memory as bench
from mcrs_benchmarks import memory_anchors

pytestmark = pytest.mark.slow

NUMBER = r"([\d,]+(?:\.\d+)?)"
TINY = ["--entries", "3000", "--map", "map10", "--episodes", "2", "--lookups", "200", "--repeats", "1"]


JUDGED = (
    "lookup_ms",
    "lookup_cpu_ms",
    "insert_ms",
    "insert_cpu_ms",
    "reembed_s",
    "reembed_cpu_s",
    "buffer_gib",
)
GOALS = {
    "lookup_ms": "<= 20",
    "lookup_cpu_ms": "<= 20",
    "insert_ms": "<= 50",
    "insert_cpu_ms": "<= 50",
    "reembed_s": "<= 10",
    "reembed_cpu_s": "<= 10",
    "buffer_gib": "<= 1.5",
}


def run(capsys: pytest.CaptureFixture[str], argv: list[str], path: Path) -> tuple[str, dict[str, Any]]:
    """The printed text and the JSON report of one run."""
    threads = torch.get_num_threads()
    assert bench.main([*argv, "--json", str(path)]) == 0
    assert torch.get_num_threads() == threads  # restored
    out = capsys.readouterr().out
    assert out.rstrip().endswith(f"results as JSON: {path}")
    return out, json.loads(path.read_text())


def test_tiny_run_prints_every_figure(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    out, report = run(capsys, [*TINY, "--threads", "1"], tmp_path / "m.json")
    figures = report["figures"]
    assert report["benchmark"] == "mcrs-bench-memory" and report["arguments"]["entries"] == 3000
    assert report["machine"]["torch_threads"] == 1
    assert "command: mcrs-bench-memory --entries 3000 --map map10" in out
    assert "torch threads=1," in out and "load average" in out
    reembed = re.search(
        rf"^re-embed 3,000 states \(refresh_keys, chunks of 4096\): {NUMBER} s \(.*; cpu {NUMBER} s\)",
        out,
        re.M,
    )
    insert = re.search(
        rf"^insert 100 transitions: {NUMBER} ms \(of which the CNN keys {NUMBER} ms; cpu {NUMBER} ms\)",
        out,
        re.M,
    )
    upkeep = re.search(
        rf"^index upkeep: merging recent records {NUMBER} ms every ~{NUMBER} insertions, purging rebuild "
        rf"{NUMBER} s every ~{NUMBER}: {NUMBER} ms per insertion amortised$",
        out,
        re.M,
    )
    lookup = re.search(
        rf"^look-up 200 keys: {NUMBER} ms \({NUMBER} hits; cpu {NUMBER} ms\); entries within the tolerance "
        rf"of a key that hits: mean {NUMBER}, median {NUMBER}$",
        out,
        re.M,
    )
    ratio = re.search(
        rf"^reference \((?:scipy cKDTree|our grid index), one query per key in Python[^)]*\): build {NUMBER} s, "
        rf"queries {NUMBER} ms; "
        rf"ratio reference / ours = {NUMBER}x; same entries found: 200 of 200$",
        out,
        re.M,
    )
    tree = re.search(
        rf"^anchor scipy cKDTree, batched \(query_ball_point p=inf, 1 worker\): build {NUMBER} s .*, query "
        rf"{NUMBER} ms .*; ratio query / ours = {NUMBER}x; same entries found: 200 of 200$",
        out,
        re.M,
    )
    size = re.search(rf"^buffer: {NUMBER} GiB held \(nbytes\); process resident memory growth", out, re.M)
    for match in (reembed, insert, upkeep, lookup, ratio, tree, size):
        assert match is not None, out
    assert re.search(r"^anchor faiss(: not installed| IndexFlat .* same entries found: 32 of 32)$", out, re.M)
    assert float(insert.group(1)) > 0 and float(lookup.group(1)) > 0
    assert int(lookup.group(2)) >= 100  # the stored half of the keys are hits
    assert "goals: not judged" in out
    # The JSON holds the printed values, with their goals, not judged at these sizes.
    for name, goal in GOALS.items():
        assert figures[name]["goal"] == goal and figures[name]["passed"] is None, name
        assert figures[name]["not_judged"], name
    for name, match, group in (
        ("reembed_s", reembed, 1),
        ("reembed_cpu_s", reembed, 2),
        ("insert_ms", insert, 1),
        ("insert_embed_ms", insert, 2),
        ("insert_cpu_ms", insert, 3),
        ("upkeep_ms_per_insertion", upkeep, 5),
        ("lookup_ms", lookup, 1),
        ("lookup_cpu_ms", lookup, 3),
        ("reference_ms", ratio, 2),
        ("ratio", ratio, 3),
        ("kdtree_batched.query_ms", tree, 2),
        ("kdtree_batched.ratio", tree, 3),
        ("buffer_gib", size, 1),
    ):
        printed = match.group(group).replace(",", "")
        decimals = len(printed.partition(".")[2])
        assert f"{figures[name]['value']:.{decimals}f}" == printed, name
        assert figures[name]["value"] > 0, name
    assert figures["entries"]["value"] == 3000
    assert figures["lookup_hits"]["value"] == int(lookup.group(2)) >= 100
    for name in ("reference_same_entries", "kdtree_batched.same_entries"):
        assert figures[name]["value"] == 200 and figures[name]["passed"] is True, name
    assert figures["ratio"]["valid"] is True and figures["kdtree_batched.ratio"]["valid"] is True
    assert "faiss.ratio" in figures
    assert report["passed"] is True  # only the agreement of the references is judged at these sizes


def _tiny_goal_sizes(monkeypatch: pytest.MonkeyPatch) -> None:
    """Pretend tiny sizes are the goal sizes, so verdicts are judged without a 1M buffer."""
    for name, value in (
        ("GOAL_ENTRIES", 3000),
        ("GOAL_MAP", "map10"),
        ("GOAL_EPISODES", 2),
        ("GOAL_LOOKUPS", 200),
    ):
        monkeypatch.setattr(bench, name, value)


def test_goal_lines_at_the_goal_sizes(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    _tiny_goal_sizes(monkeypatch)
    out, report = run(capsys, ["--repeats", "1", "--threads", "1"], tmp_path / "m.json")
    goals = out[out.index("\ngoals (wall clock;") :]
    figures = report["figures"]
    verdict = {True: "PASS", False: "FAIL"}
    for name, goal in GOALS.items():
        assert figures[name]["goal"] == goal and figures[name]["not_judged"] is None, name
        assert figures[name]["passed"] in (True, False), name
    assert figures["buffer_gib"]["passed"] is True  # 3,000 entries
    for label, wall, cpu in (
        ("look-up of 200 keys at 1M entries <= 20 ms:", "lookup_ms", "lookup_cpu_ms"),
        ("insertion of 100 transitions <= 50 ms:", "insert_ms", "insert_cpu_ms"),
        ("re-embedding 1M map10 states (CNN) <= 10 s:", "reembed_s", "reembed_cpu_s"),
    ):
        line = re.search(rf"^  {re.escape(label)} .* (PASS|FAIL) \(cpu .* (PASS|FAIL)\)$", goals, re.M)
        assert line is not None, goals
        assert line.groups() == (verdict[figures[wall]["passed"]], verdict[figures[cpu]["passed"]])
    for label, name in (("buffer <= 1.5 GiB:", "buffer_gib"),):
        line = re.search(rf"^  {re.escape(label)} .* (PASS|FAIL)$", goals, re.M)
        assert line is not None, goals
        assert line.group(1) == verdict[figures[name]["passed"]]
    judged = [figures[name]["passed"] for name in GOALS] + [figures["reference_same_entries"]["passed"]]
    assert report["passed"] is all(judged)


def test_a_reference_that_finds_other_entries_fails(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """A comparison is void when the reference finds other entries than ours: FAIL, whatever the ratio."""
    _tiny_goal_sizes(monkeypatch)
    real = bench.reference_lookups

    def wrong(memory: Any, keys: torch.Tensor) -> tuple[str, float, float, torch.Tensor]:
        label, build, loop, found = real(memory, keys)
        found = found.clone()
        found[0] = -2  # no slot
        return label, build, loop, found

    monkeypatch.setattr(bench, "reference_lookups", wrong)
    out, report = run(capsys, ["--repeats", "1", "--threads", "1"], tmp_path / "m.json")
    figures = report["figures"]
    assert figures["reference_same_entries"] == {
        **figures["reference_same_entries"],
        "value": 199,
        "passed": False,
    }
    assert figures["ratio"]["valid"] is False and figures["ratio"]["goal"] is None  # a ratio, not a goal
    assert report["passed"] is False
    assert "same entries found: 199 of 200" in out, out


def test_without_scipy_the_reference_is_our_index_one_key_at_a_time(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    import sys

    monkeypatch.setitem(sys.modules, "scipy.spatial", None)  # import fails
    monkeypatch.setitem(sys.modules, "faiss", None)
    out, report = run(capsys, [*TINY, "--threads", "1"], tmp_path / "m.json")
    figures = report["figures"]
    assert figures["kdtree_batched.ratio"]["value"] is None and "kdtree_batched.same_entries" not in figures
    assert figures["faiss.ratio"]["note"] == "faiss not installed"
    assert figures["reference_same_entries"]["passed"] is True
    assert "our grid index" in figures["ratio"]["note"]
    assert "anchor scipy cKDTree, batched: scipy not installed" in out
    assert "anchor faiss: not installed" in out
    assert re.search(
        r"^reference \(our grid index, one query per key in Python \(scipy not installed\)\): .*"
        r"same entries found: 200 of 200$",
        out,
        re.M,
    ), out


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--entries", "0"], "--entries must be >= 1, got 0"),
        (["--lookups", "-3"], "--lookups must be >= 1, got -3"),
        (["--chunk", "0"], "--chunk must be >= 1, got 0"),
        (["--delta", "0"], "--delta must be > 0, got 0.0"),
        (["--threads", "-1"], "--threads must be >= 0, got -1"),
    ],
)
def test_bad_arguments_are_refused(capsys: pytest.CaptureFixture[str], argv: list[str], message: str) -> None:
    with pytest.raises(SystemExit):
        bench.main([*argv, "--json", "none"])
    err = capsys.readouterr().err
    assert err.strip().splitlines()[-1].endswith(message), err


@pytest.mark.parametrize("shape", ["ball", "box"])
def test_the_anchors_find_what_our_index_finds(shape: str) -> None:
    """The batched cKDTree and faiss anchors answer exactly as the memory does, in both shapes (scipy and
    faiss are optional: skipped without them)."""
    pytest.importorskip("scipy.spatial")
    from mcrs.env.config import scenario
    from mcrs.memory.codec import StateCodec
    from mcrs.memory.episodic import EpisodicMemory
    from mcrs.models.embeddings import make_embedding

    config = scenario("map10")
    embedding = make_embedding("cnn", config.state_dim, (config.width, config.height), seed=0).eval()
    memory = EpisodicMemory(
        embedding, StateCodec(config), capacity=4000, tolerance=0.2, max_steps=config.max_steps, shape=shape
    )
    bench.fill(memory, config, 4000, seed=3)
    memory.refresh_keys()
    generator = torch.Generator().manual_seed(0)
    keys = memory.keys[torch.randint(0, 4000, (300,), generator=generator)]
    keys = torch.cat([keys + torch.randn(keys.shape, generator=generator) * memory.index.std * 0.1, keys * 3])
    _, hit, found = memory.lookup_keys(keys)
    assert 0 < int(hit.sum()) < len(keys)
    tree = memory_anchors.kdtree_batched(memory, keys, workers=1)
    assert torch.equal(tree["found"], found)
    flat = memory_anchors.faiss_flat(memory, keys)
    if flat is not None:
        assert torch.equal(flat["found"], found)
