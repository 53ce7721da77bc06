"""The episodic-memory benchmark runs end to end at a tiny size and prints every figure (no timing asserts)."""

from __future__ import annotations

import re

import pytest
import torch

from mcrs.benchmarks import memory as bench
from mcrs.benchmarks import memory_anchors

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
    goals = out[out.index("\ngoals (wall clock;") :]
    for label in (
        "look-up of 200 keys at 1M entries <= 20 ms:",
        "insertion of 100 transitions <= 50 ms:",
        "re-embedding 1M map10 states (CNN) <= 10 s:",
        "buffer <= 1.5 GiB:",
        "look-up >= 20x the per-transition reference:",
    ):
        assert re.search(
            rf"^  {re.escape(label)} .* (PASS|FAIL) \(cpu .* (PASS|FAIL)\)$|^  {re.escape(label)} .* (PASS|FAIL)$",
            goals,
            re.M,
        ), goals


def test_without_scipy_the_reference_is_our_index_one_key_at_a_time(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import sys

    monkeypatch.setitem(sys.modules, "scipy.spatial", None)  # import fails
    monkeypatch.setitem(sys.modules, "faiss", None)
    out = run(capsys, [*TINY, "--threads", "1"])
    assert "anchor scipy cKDTree, batched: scipy not installed" in out
    assert "anchor faiss: not installed" in out
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
        embedding, StateCodec(config), capacity=4000, delta=0.2, max_steps=config.max_steps, shape=shape
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
