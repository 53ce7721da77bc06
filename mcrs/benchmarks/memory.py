"""Episodic-memory benchmark (``mcrs-bench-memory``, ``python -m mcrs.benchmarks.memory``).

Why: the episodic buffer D_E sits on the training loop's hot path (an insertion per collected batch, a
look-up per learner batch, a re-embedding of every stored state per embedding update) and holds a million
states. This fills a memory with ``--entries`` states of ``--map`` and prints, with PASS/FAIL at the
default sizes (1M map20 entries):

* insertion of 32 episodes x 100 steps (Algorithm 1 with the CNN embedding; median of ``--repeats``
  fresh batches into the full buffer, which evicts): <= 50 ms;
* look-up of 3,200 keys: <= 20 ms, and >= 20x the reference approach of EMC/EMU (one scipy
  ``cKDTree.query`` per transition in a Python loop, tree built once beforehand - its build time is
  printed separately and not charged to it); the two must find the same entries. scipy is not a
  dependency of the package: without it the stand-in reference is our index queried one key at a time;
* re-embedding every stored state with the CNN encoder (``refresh_keys``: decode, embed, rebuild the
  index): <= 10 s;
* the buffer's size (``nbytes``) <= 1.5 GiB, with the process's resident-memory growth next to it.

The buffer is filled quickly, not by a million insertions: real env rollouts (random allowed actions, 1024
episodes) are tiled and perturbed - a few extra readings on random cells, UAVs moved by one cell - into
valid compact states written straight into the storage, then ``refresh_keys`` computes every key (that run
is the re-embedding figure). At the default tolerance (eq. 35's volume, a box of half-side 0.095) the key
distribution matters: a look-up verifies every entry of 16 cells of twice that side. A run's buffer holds
states that Algorithm 1 kept apart (a state within the tolerance of an entry merges into it); the fill's
perturbed copies of 1024 episodes (about 10 per state at 1M entries) are denser than that, so the figures
are an upper bound.
"""

from __future__ import annotations

import argparse
import gc
import itertools
import os
import shlex
import statistics
import sys
import time
from collections.abc import Callable, Sequence

import numpy as np
import torch

from mcrs.benchmarks.common import benchmark_process, load_average, pass_fail
from mcrs.benchmarks.env_throughput import resident_bytes
from mcrs.env.config import SCENARIOS, EnvConfig, scenario
from mcrs.env.core import MCRSCore
from mcrs.experiment.config import MemoryConfig
from mcrs.memory.codec import StateCodec
from mcrs.memory.delta import DELTA_RULES, match_tolerance
from mcrs.memory.episodic import EpisodicMemory
from mcrs.memory.index import RECENT_MIN, RECENT_SHARE, SHAPES, squared_distance

GOAL_MAP = "map20"
GOAL_ENTRIES = 1_000_000
GOAL_EPISODES = 32
GOAL_LOOKUPS = 3200
GOAL_LOOKUP_MS = 20.0
GOAL_INSERT_MS = 50.0
GOAL_REEMBED_S = 10.0
GOAL_GIB = 1.5
GOAL_RATIO = 20.0
FAISS_KEYS = 32  # faiss's exact index is brute force (seconds per 100 keys): timed on this many, scaled
GIB = 2**30
EXTRA_READS = 8  # readings added to random cells of each synthetic state
FILL_EPISODES = 1024  # rolled-out episodes the synthetic states are perturbed copies of


def rollout(config: EnvConfig, episodes: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A collector-like batch: ``state [E, T, D]``, ``state_counts [E, T, cells, 2]``, ``reward [E, T]``."""
    core = MCRSCore(config.replace(num_envs=episodes, device="cpu"))
    core.seed(seed)
    generator = torch.Generator().manual_seed(seed)
    result = core.reset()
    states, counts, rewards = [], [], []
    for _ in range(config.max_steps):
        states.append(result.state)
        counts.append(result.state_counts)
        scores = torch.rand(result.action_mask.shape, generator=generator).masked_fill(
            ~result.action_mask, -1
        )
        result = core.step(scores.argmax(-1))
        rewards.append(result.reward)
    return torch.stack(states, 1), torch.stack(counts, 1), torch.stack(rewards, 1)


def fill(memory: EpisodicMemory, config: EnvConfig, entries: int, seed: int, chunk: int = 65536) -> None:
    """Write ``entries`` perturbed copies of rolled-out states into the storage (keys left to refresh_keys).

    Bypasses Algorithm 1 on purpose: a million insertions would take minutes and measure nothing new.
    """
    codec = memory.codec
    state, counts, _ = rollout(config, FILL_EPISODES, seed)
    base_codes, base_positions = codec.encode(counts.flatten(0, 1), state.flatten(0, 1))
    base_step = torch.arange(config.max_steps, dtype=torch.int16).repeat(state.shape[0])
    generator = torch.Generator().manual_seed(seed + 1)
    grid_max = torch.tensor(codec.grid_max, dtype=torch.int16)
    for start in range(0, entries, chunk):
        n = min(chunk, entries - start)
        pick = torch.randint(0, base_codes.shape[0], (n,), generator=generator)
        codes = base_codes[pick].to(torch.int16).view(n, -1)
        extra = torch.randint(0, codes.shape[1], (n, EXTRA_READS), generator=generator)
        codes.scatter_add_(1, extra, torch.ones_like(extra, dtype=torch.int16))
        positions = base_positions[pick].to(torch.int16)
        moves = torch.randint(-1, 2, (n, config.n_uavs, 2), generator=generator, dtype=torch.int16)
        positions[:, : config.n_uavs] = torch.minimum(
            (positions[:, : config.n_uavs] + moves).clamp(min=0), grid_max
        )
        slots = slice(start, start + n)
        memory.codes[slots] = codes.view(n, codec.n_cells, 2).clamp(max=255).to(memory.codes.dtype)
        memory.positions[slots] = positions.to(memory.positions.dtype)
        memory.step[slots] = base_step[pick]
        memory.returns[slots] = torch.randn(n, generator=generator) * 50 + 200
    memory.live[:entries] = True
    memory.start, memory.size = 0, entries


def median_seconds(run: Callable[[], object], repeats: int) -> tuple[float, float]:
    """Median wall-clock and process-CPU seconds of ``repeats`` calls after one warm-up call.

    The CPU time is shown beside the wall clock: on a loaded machine (other processes on the same cores)
    the wall clock also counts the time the process waited, the CPU time does not.
    """
    run()
    wall, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        run()
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return statistics.median(wall), statistics.median(cpu)


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
    tolerance = memory.delta
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
    radius = memory.delta * (1 + 1e-6)  # float64 tree vs float32 test: the exact test decides
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
    radius = memory.delta * (1 + 1e-6)
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


def upkeep(memory: EpisodicMemory, added: int) -> str:
    """The index upkeep that the median insertion does not show, amortised over ``added`` records per batch:
    merging the recent records into the main ones (every ``RECENT_SHARE``-th of the records) and the
    memory's stale-record purge (a rebuild, when stale records pass ``stale_fraction`` of the entries)."""
    index = memory.index
    start = time.perf_counter()
    index.flush()
    merge_s = time.perf_counter() - start
    start = time.perf_counter()
    memory.rebuild_index(refresh=False)
    rebuild_s = time.perf_counter() - start
    every_merge = max(RECENT_MIN, len(index) // RECENT_SHARE) / max(added, 1)
    every_rebuild = memory.stale_fraction * len(memory) / max(added, 1)  # stale: evicted + shifted records
    return (
        f"index upkeep: merging recent records {merge_s * 1e3:.1f} ms every ~{every_merge:.0f} insertions, "
        f"purging rebuild {rebuild_s:.2f} s every ~{every_rebuild:.0f}: "
        f"{(merge_s / every_merge + rebuild_s / every_rebuild) * 1e3:.1f} ms per insertion amortised"
    )


def anchors(memory: EpisodicMemory, keys: torch.Tensor, found: torch.Tensor, lookup_s: float) -> None:
    """Print the fair anchors (batched cKDTree, faiss) beside our look-up, as ratios anchor / ours."""
    n = len(keys)
    try:
        tree = kdtree_batched(memory, keys, workers=torch.get_num_threads())
    except ImportError:
        print("anchor scipy cKDTree, batched: scipy not installed", flush=True)
    else:
        same = int((tree["found"] == found).sum())
        print(
            f"anchor scipy cKDTree, batched ({'query_ball_point p=inf' if memory.shape == 'box' else 'query k=1'}, "
            f"{torch.get_num_threads()} worker): build {tree['build_s']:.2f} s (what an insertion would "
            f"rebuild), query {tree['query_s'] * 1e3:.1f} ms (+ {tree['select_s'] * 1e3:.1f} ms to pick the "
            f"nearest inside); ratio query / ours = {tree['query_s'] / lookup_s:.1f}x; same entries found: "
            f"{same:,} of {n:,}",
            flush=True,
        )
    few = min(n, FAISS_KEYS)
    flat = faiss_flat(memory, keys[:few])
    if flat is None:
        print("anchor faiss: not installed", flush=True)
        return
    same = int((flat["found"] == found[:few]).sum())
    scaled = flat["query_s"] * n / few
    print(
        f"anchor faiss IndexFlat range_search (exact, brute force), {few:,} of the keys: "
        f"{flat['query_s'] * 1e3:.1f} ms, {scaled * 1e3:.0f} ms scaled to {n:,}; ratio / ours = "
        f"{scaled / lookup_s:.0f}x; same entries found: {same:,} of {few:,}",
        flush=True,
    )


def _parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="mcrs-bench-memory",
        description="Insertion, look-up, re-embedding and size of the episodic memory D_E, with goals.",
    )
    parser.add_argument("--entries", type=int, default=GOAL_ENTRIES, help="entries in the filled buffer")
    parser.add_argument("--map", choices=SCENARIOS, default=GOAL_MAP, help="env preset")
    parser.add_argument("--episodes", type=int, default=GOAL_EPISODES, help="episodes per inserted batch")
    parser.add_argument("--lookups", type=int, default=GOAL_LOOKUPS, help="keys per timed look-up")
    parser.add_argument("--repeats", type=int, default=5, help="timed repetitions (median) of insert/look-up")
    parser.add_argument("--chunk", type=int, default=4096, help="states per chunk when re-embedding")
    parser.add_argument("--threads", type=int, default=0, help="torch intra-op threads (0: torch's default)")
    defaults = MemoryConfig()
    parser.add_argument("--delta", type=float, default=defaults.delta, help="the paper's delta (table 3)")
    parser.add_argument(
        "--delta-rule",
        choices=DELTA_RULES,
        default=defaults.delta_rule,
        help="what delta means (docs/MEMORY.md)",
    )
    parser.add_argument(
        "--neighbourhood", choices=SHAPES, default=defaults.neighbourhood, help="ball or EMU's box"
    )
    args = parser.parse_args(argv)
    if not args.delta > 0:
        parser.error(f"--delta must be > 0, got {args.delta}")
    for name in ("entries", "episodes", "lookups", "repeats", "chunk"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    if args.threads < 0:
        parser.error(f"--threads must be >= 0, got {args.threads}")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark and print the figures and the goals."""
    command = shlex.join(["mcrs-bench-memory", *(sys.argv[1:] if argv is None else argv)])
    args = _parse_args(argv)
    with benchmark_process(args.threads):
        _run(args, command)
    return 0


def _run(args: argparse.Namespace, command: str) -> None:
    from mcrs.models.embeddings import make_embedding

    config = scenario(args.map)
    judged = (args.entries, args.map, args.episodes, args.lookups) == (
        GOAL_ENTRIES,
        GOAL_MAP,
        GOAL_EPISODES,
        GOAL_LOOKUPS,
    )
    transitions = args.episodes * config.max_steps
    tolerance = match_tolerance(args.delta, args.delta_rule, args.neighbourhood, 4)
    print(
        f"MCRS episodic-memory benchmark: device=cpu, torch threads={torch.get_num_threads()}, "
        f"cpus={os.cpu_count()}, load average {load_average()}\n"
        f"command: {command}\n"
        f"{args.map}: state {config.state_dim} floats, T={config.max_steps}; {args.entries:,} entries, "
        f"CNN embedding (key_dim 4), delta {args.delta:g} read as {args.delta_rule} ({args.neighbourhood} of "
        f"tolerance {tolerance:.4g}); insert batches of {args.episodes} episodes "
        f"({transitions:,} transitions); look-ups of {args.lookups:,} keys; medians of {args.repeats}",
        flush=True,
    )
    embedding = make_embedding("cnn", config.state_dim, (config.width, config.height), seed=0).eval()
    codec = StateCodec(config)
    gc.collect()
    rss_before = resident_bytes()
    memory = EpisodicMemory(
        embedding,
        codec,
        capacity=max(args.entries, transitions),
        delta=tolerance,
        max_steps=config.max_steps,
        shape=args.neighbourhood,
    )
    start = time.perf_counter()
    fill(memory, config, args.entries, seed=1)
    fill_s = time.perf_counter() - start

    # Re-embedding: every stored state decoded, embedded, and the index rebuilt.
    start, start_cpu = time.perf_counter(), time.process_time()
    memory.refresh_keys(chunk=args.chunk)
    reembed_s, reembed_cpu = time.perf_counter() - start, time.process_time() - start_cpu
    print(
        f"\nfill (synthetic states written to the storage): {fill_s:.2f} s\n"
        f"re-embed {len(memory):,} states (refresh_keys, chunks of {args.chunk}): {reembed_s:.2f} s "
        f"({reembed_s / len(memory) * 1e6:.2f} us/state; cpu {reembed_cpu:.2f} s)",
        flush=True,
    )

    # Insertion: fresh batches into the full buffer (each evicts as many entries as it has transitions).
    batches = [rollout(config, args.episodes, seed=100 + i) for i in range(args.repeats + 1)]
    queue = list(batches)
    insert_s, insert_cpu = median_seconds(lambda: memory.insert(*queue.pop()), args.repeats)
    state, _, _ = batches[0]
    time_in = memory.normalised_time(torch.arange(config.max_steps)).expand(args.episodes, -1)
    with torch.no_grad():
        embed_s, _ = median_seconds(lambda: embedding(state, time_in), args.repeats)
    stats = memory.insert(*rollout(config, args.episodes, seed=99))
    print(
        f"insert {transitions:,} transitions: {insert_s * 1e3:.2f} ms (of which the CNN keys "
        f"{embed_s * 1e3:.2f} ms; cpu {insert_cpu * 1e3:.2f} ms); last batch: {stats.new} new, "
        f"{stats.hits} hits, {stats.shifted} shifts, {stats.evicted} evicted",
        flush=True,
    )
    print(upkeep(memory, stats.new + stats.shifted), flush=True)

    # Look-ups: half keys of stored entries (nudged: hits), half keys of a fresh batch (mostly misses).
    generator = torch.Generator().manual_seed(7)
    slots = memory.live_slots()
    stored = memory.keys[slots[torch.randint(0, len(slots), (args.lookups // 2,), generator=generator)]]
    stored = stored + memory.index.std * tolerance * 0.1
    fresh_state = rollout(config, max(1, -(-args.lookups // config.max_steps)), seed=200)[0]
    fresh_time = memory.normalised_time(torch.arange(config.max_steps)).expand(fresh_state.shape[0], -1)
    with torch.no_grad():
        fresh = embedding(fresh_state, fresh_time).reshape(-1, memory.key_dim)
    keys = torch.cat([stored, fresh[: args.lookups - stored.shape[0]]])
    lookup_s, lookup_cpu = median_seconds(lambda: memory.lookup_keys(keys), args.repeats)
    _, hit, found = memory.lookup_keys(keys)
    query, _, _ = memory.index.within(memory.index.standardise(keys), memory.keys, memory.live)
    near = torch.bincount(query, minlength=len(keys))[hit].to(torch.float32)
    label, build_s, loop_s, ref_found = reference_lookups(memory, keys)
    agree = int((ref_found == found).sum())
    ratio = loop_s / lookup_s
    print(
        f"look-up {len(keys):,} keys: {lookup_s * 1e3:.2f} ms ({int(hit.sum()):,} hits; cpu "
        f"{lookup_cpu * 1e3:.2f} ms); entries within the tolerance of a key that hits: mean "
        f"{float(near.mean()) if near.numel() else 0.0:.1f}, median {float(near.median()) if near.numel() else 0.0:.0f}\n"
        f"reference ({label}): build {build_s:.2f} s, "
        f"queries {loop_s * 1e3:.1f} ms; ratio reference / ours = {ratio:.1f}x; "
        f"same entries found: {agree:,} of {len(keys):,}",
        flush=True,
    )
    anchors(memory, keys, found, lookup_s)

    gc.collect()
    rss_after = resident_bytes()
    rss = "n/a" if rss_before is None or rss_after is None else f"{(rss_after - rss_before) / GIB:.3f} GiB"
    nbytes = memory.nbytes()
    print(f"buffer: {nbytes / GIB:.3f} GiB held (nbytes); process resident memory growth {rss}", flush=True)

    if not judged:
        print(
            "\ngoals: not judged (they apply to --entries 1000000 --map map20 --episodes 32 --lookups 3200)"
        )
        return
    lines = [
        f"look-up of {GOAL_LOOKUPS:,} keys at 1M entries <= {GOAL_LOOKUP_MS:g} ms: {lookup_s * 1e3:.2f} ms "
        f"{pass_fail(lookup_s * 1e3 <= GOAL_LOOKUP_MS)} (cpu {lookup_cpu * 1e3:.2f} ms "
        f"{pass_fail(lookup_cpu * 1e3 <= GOAL_LOOKUP_MS)})",
        f"insertion of {transitions:,} transitions <= {GOAL_INSERT_MS:g} ms: {insert_s * 1e3:.2f} ms "
        f"{pass_fail(insert_s * 1e3 <= GOAL_INSERT_MS)} (cpu {insert_cpu * 1e3:.2f} ms "
        f"{pass_fail(insert_cpu * 1e3 <= GOAL_INSERT_MS)})",
        f"re-embedding 1M {GOAL_MAP} states (CNN) <= {GOAL_REEMBED_S:g} s: {reembed_s:.2f} s "
        f"{pass_fail(reembed_s <= GOAL_REEMBED_S)} (cpu {reembed_cpu:.2f} s "
        f"{pass_fail(reembed_cpu <= GOAL_REEMBED_S)})",
        f"buffer <= {GOAL_GIB:g} GiB: {nbytes / GIB:.3f} GiB {pass_fail(nbytes <= GOAL_GIB * GIB)}",
        f"look-up >= {GOAL_RATIO:g}x the per-transition reference: {ratio:.1f}x "
        f"{pass_fail(ratio >= GOAL_RATIO and agree == len(keys))}",
    ]
    print(
        f"\ngoals (wall clock; in brackets the process CPU time, what a quiet machine's wall clock comes "
        f"close to when the load average {load_average()} is above the {os.cpu_count()} cores):\n  "
        + "\n  ".join(lines),
        flush=True,
    )


if __name__ == "__main__":
    raise SystemExit(main())
