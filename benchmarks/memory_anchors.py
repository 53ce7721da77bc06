"""The anchors of the memory benchmark (``mcrs-bench-memory``): the same look-ups done by scipy and faiss.

Why: a speed claim needs a fair comparison. EMC/EMU query a cKDTree one transition at a time (the
reference kept from the first version of the benchmark), but scipy can query a whole batch at once, and
faiss is the usual library for nearest neighbours. Each anchor must find exactly the entries our index
finds (the same float32 test decides), and its time is printed beside ours as a ratio and recorded in
the benchmark's report. scipy and faiss are optional: without them the anchor says so.
"""

from __future__ import annotations

import itertools
import time

import numpy as np
import torch
from mcrs_benchmarks.harness import Goal, Report

from mcrs.memory.episodic import EpisodicMemory
from mcrs.memory.index import squared_distance

FAISS_KEYS = 32  # faiss's exact index is brute force (seconds per 100 keys): timed on this many, scaled


def reference_lookups(memory: EpisodicMemory, keys: torch.Tensor) -> tuple[str, float, float, torch.Tensor]:
    """EMC/EMU's way: a cKDTree over the standardised keys, then one query per transition in Python.

    Returns (label, build seconds, query-loop seconds, slot found or -1 per key). Without scipy (not a
    dependency of the package), the stand-in is our own index queried one key at a time.
    """
    slots = memory.live_slots()
    queries = memory.index.standardise(keys)
    found = []
    try:
        from scipy.spatial import cKDTree
    except ImportError:
        start = time.perf_counter()
        for z in queries.split(1):  # one transition at a time
            slot, _ = memory.index.nearest(z, memory.keys, memory.live)
            found.append(int(slot))
        loop = time.perf_counter() - start
        return (
            "our grid index, one query per key in Python (scipy not installed)",
            0.0,
            loop,
            torch.tensor(found),
        )
    stored = memory.index.standardise(memory.keys[slots]).numpy()
    returns = memory.returns[slots].numpy()
    tolerance = memory.tolerance
    start = time.perf_counter()
    tree = cKDTree(stored)
    build = time.perf_counter() - start
    start = time.perf_counter()
    for z in queries.numpy():  # one transition at a time, as the reference code does
        if memory.shape == "box":  # the entries in the box (Chebyshev ball), then the nearest of them
            inside = tree.query_ball_point(z, r=tolerance, p=np.inf)
            if inside:
                d2 = ((stored[inside] - z) ** 2).sum(1)
                ind = inside[int(np.argmin(d2))]
                _ = returns[ind]
                found.append(int(slots[ind]))
            else:
                found.append(-1)
            continue
        dist, ind = tree.query(z, k=1)
        if dist < tolerance:
            _ = returns[ind]
            found.append(int(slots[ind]))
        else:
            found.append(-1)
    loop = time.perf_counter() - start
    return "scipy cKDTree, one query per key in Python", build, loop, torch.tensor(found)


def exact_choice(
    memory: EpisodicMemory, z: np.ndarray, owner: np.ndarray, row: np.ndarray, stored: np.ndarray
) -> np.ndarray:
    """Our answer from candidate pairs (query ``owner``, stored ``row``) that a library found: the exact
    float32 test of the index's shape, then the nearest (lowest row on ties) per query; -1 where none."""
    a, b = torch.from_numpy(z[owner]), torch.from_numpy(stored[row])
    d2 = squared_distance(a, b)
    inside = memory.index.matches(a, b, d2).numpy()
    owner, row, d2 = owner[inside], row[inside], d2.numpy()[inside]
    order = np.lexsort((row, d2, owner))
    owner, row = owner[order], row[order]
    first = np.ones(owner.size, dtype=bool)
    first[1:] = owner[1:] != owner[:-1]
    best = np.full(z.shape[0], -1, dtype=np.int64)
    best[owner[first]] = row[first]
    return best


def kdtree_batched(
    memory: EpisodicMemory, keys: torch.Tensor, workers: int
) -> dict[str, float | torch.Tensor]:
    """The fair anchor (scipy is optional): one batched cKDTree query of all keys in the norm of the shape
    (box: ``query_ball_point`` with p = inf; ball: ``query`` k = 1 with ``distance_upper_bound``), radius a
    hair above the tolerance, then our exact float32 test. Returns its build and query seconds (the query
    alone, the cheapest part; ``select_s`` the exact choice after it) and the slot found per key."""
    from scipy.spatial import cKDTree

    slots = memory.live_slots()
    stored = memory.index.standardise(memory.keys[slots]).numpy()
    z = memory.index.standardise(keys).numpy()
    radius = memory.tolerance * (1 + 1e-6)  # float64 tree vs float32 test: the exact test decides
    start = time.perf_counter()
    tree = cKDTree(stored)
    build = time.perf_counter() - start
    start = time.perf_counter()
    if memory.shape == "box":
        lists = tree.query_ball_point(z, r=radius, p=np.inf, workers=workers, return_sorted=False)
        query = time.perf_counter() - start
        start = time.perf_counter()
        lengths = np.fromiter(map(len, lists), dtype=np.int64, count=len(lists))
        row = np.fromiter(itertools.chain.from_iterable(lists), dtype=np.int64, count=int(lengths.sum()))
        owner = np.repeat(np.arange(len(lists)), lengths)
    else:
        _, nearest = tree.query(z, k=1, distance_upper_bound=radius, workers=workers)
        query = time.perf_counter() - start
        start = time.perf_counter()
        owner = np.flatnonzero(nearest < stored.shape[0])
        row = nearest[owner]
    best = exact_choice(memory, z, owner, row, stored)
    select = time.perf_counter() - start
    found = torch.where(torch.from_numpy(best) >= 0, slots[torch.from_numpy(best).clamp(min=0)], -1)
    return {"build_s": build, "query_s": query, "select_s": select, "found": found}


def faiss_flat(memory: EpisodicMemory, keys: torch.Tensor) -> dict[str, float | torch.Tensor] | None:
    """faiss (optional): its exact index for this metric, ``IndexFlat`` (brute force; L-inf for the box,
    L2 for the ball) with ``range_search``, then our exact test. None without faiss."""
    try:
        import faiss
    except ImportError:
        return None
    faiss.omp_set_num_threads(max(1, torch.get_num_threads()))
    slots = memory.live_slots()
    stored = np.ascontiguousarray(memory.index.standardise(memory.keys[slots]).numpy())
    z = np.ascontiguousarray(memory.index.standardise(keys).numpy())
    radius = memory.tolerance * (1 + 1e-6)
    box = memory.shape == "box"
    index = faiss.IndexFlat(stored.shape[1], faiss.METRIC_Linf if box else faiss.METRIC_L2)
    index.add(stored)
    start = time.perf_counter()
    limits, _, row = index.range_search(z, radius if box else radius * radius)
    query = time.perf_counter() - start
    owner = np.repeat(np.arange(z.shape[0]), np.diff(limits).astype(np.int64))
    best = exact_choice(memory, z, owner, row.astype(np.int64), stored)
    found = torch.where(torch.from_numpy(best) >= 0, slots[torch.from_numpy(best).clamp(min=0)], -1)
    return {"query_s": query, "found": found}


def anchors(
    memory: EpisodicMemory, keys: torch.Tensor, found: torch.Tensor, lookup_s: float, report: Report
) -> None:
    """Print the fair anchors (batched cKDTree, faiss) beside our look-up, as ratios anchor / ours, and record
    them in ``report`` (``kdtree_batched.*``, ``faiss.*``). No goal on the ratios, but an anchor that finds
    other entries than ours FAILs (``.same_entries``, goal: every key; its ratio is then void)."""
    n = len(keys)
    try:
        tree = kdtree_batched(memory, keys, workers=torch.get_num_threads())
    except ImportError:
        report.figure("kdtree_batched.ratio", None, "x", note="scipy not installed")
        print("anchor scipy cKDTree, batched: scipy not installed", flush=True)
    else:
        same = int((tree["found"] == found).sum())
        report.figure("kdtree_batched.build_s", tree["build_s"], "s", note="what an insertion would rebuild")
        report.figure("kdtree_batched.query_ms", tree["query_s"] * 1e3, "ms")
        report.figure("kdtree_batched.select_ms", tree["select_s"] * 1e3, "ms", note="the nearest inside")
        report.figure("kdtree_batched.same_entries", same, "keys", Goal(">=", n))
        ratio = report.figure(
            "kdtree_batched.ratio", tree["query_s"] / lookup_s, "x", valid=same == n, note="query / ours"
        )
        print(
            f"anchor scipy cKDTree, batched ({'query_ball_point p=inf' if memory.shape == 'box' else 'query k=1'}, "
            f"{torch.get_num_threads()} worker): build {tree['build_s']:.2f} s (what an insertion would "
            f"rebuild), query {tree['query_s'] * 1e3:.1f} ms (+ {tree['select_s'] * 1e3:.1f} ms to pick the "
            f"nearest inside); ratio query / ours = {ratio.value:.1f}x; same entries found: "
            f"{same:,} of {n:,}",
            flush=True,
        )
    few = min(n, FAISS_KEYS)
    flat = faiss_flat(memory, keys[:few])
    if flat is None:
        report.figure("faiss.ratio", None, "x", note="faiss not installed")
        print("anchor faiss: not installed", flush=True)
        return
    same = int((flat["found"] == found[:few]).sum())
    scaled = flat["query_s"] * n / few
    report.figure("faiss.query_ms", flat["query_s"] * 1e3, "ms", note=f"IndexFlat range_search, {few} keys")
    report.figure("faiss.scaled_ms", scaled * 1e3, "ms", note=f"scaled to {n} keys")
    report.figure("faiss.same_entries", same, "keys", Goal(">=", few))
    ratio = report.figure("faiss.ratio", scaled / lookup_s, "x", valid=same == few, note="scaled / ours")
    print(
        f"anchor faiss IndexFlat range_search (exact, brute force), {few:,} of the keys: "
        f"{flat['query_s'] * 1e3:.1f} ms, {scaled * 1e3:.0f} ms scaled to {n:,}; ratio / ours = "
        f"{ratio.value:.1f}x; same entries found: {same:,} of {few:,}",
        flush=True,
    )
