"""Episodic-memory benchmark (``mcrs-bench-memory``, ``python -m mcrs_benchmarks.memory``).

Why: the episodic buffer D_E sits on the training loop's hot path (an insertion per collected batch, a
look-up per learner batch, a re-embedding of every stored state per embedding update) and holds a million
states. This fills a memory with ``--entries`` states of ``--map`` and prints, with PASS/FAIL at the
default sizes (1M map20 entries):

* insertion of 32 episodes x 100 steps (Algorithm 1 with the CNN embedding; median of ``--repeats``
  fresh batches into the full buffer, which evicts): <= 50 ms;
* look-up of 3,200 keys: <= 20 ms; beside it the ratio to the reference approach of EMC/EMU (one scipy
  ``cKDTree.query`` per transition in a Python loop, tree built once beforehand - its build time is
  printed separately and not charged to it; no goal: a Python loop is not a fair anchor, the batched
  query below is); the two must find the same entries. scipy is not a
  dependency of the package: without it the stand-in reference is our index queried one key at a time.
  Beside it the fair anchors (:mod:`mcrs_benchmarks.memory_anchors`): one batched cKDTree query of all
  keys, and faiss's exact index, as ratios to ours (no goal);
* re-embedding every stored state with the CNN encoder (``refresh_keys``: decode, embed, rebuild the
  index): <= 10 s;
* the buffer's size (``nbytes``) <= 1.5 GiB, with the process's resident-memory growth next to it.

Times are wall clock with the process CPU time beside them (on a loaded machine the CPU time is the
better estimate of a quiet machine's wall clock). The figures are also written as JSON (the shared harness,
:mod:`mcrs_benchmarks.harness`): ``lookup_ms``, ``insert_ms``, ``reembed_s`` and their ``*_cpu_*`` twins,
``buffer_gib`` (judged at the default sizes only), ``ratio``, the anchors' ``kdtree_batched.*`` and
``faiss.*``; every ``*same_entries`` figure must count every key, whatever the sizes.

Two fills (``--fill``). At the default tolerance (eq. 35's volume, a box of half-side 0.095) the key
density decides the cost: every entry near a query is a candidate to test.

* ``synthetic`` (default, judged, the worst case): real env rollouts (random allowed actions, 1024
  episodes) tiled and perturbed - a few extra readings on random cells, UAVs moved by one cell - into
  ``--entries`` valid compact states written straight into the storage, then ``refresh_keys`` computes every
  key (that run is the re-embedding figure). About 10 near-copies per rolled-out state: a key that hits has
  ~17 entries within the tolerance. No run builds that: Algorithm 1 merges a state within the tolerance of
  an entry into it.
* ``algorithm1``: ``--entries`` transitions of random-policy episodes inserted through Algorithm 1, as a
  run inserts them (merges and shifts included). The buffer then holds far fewer entries (map20: about
  0.25M after 1M transitions) at the density a run sees (~3 within the tolerance of a key that hits).
"""

from __future__ import annotations

import argparse
import gc
import os
import statistics
import time
from collections.abc import Callable, Sequence

import torch
from mcrs_benchmarks.common import load_average
from mcrs_benchmarks.env_throughput import resident_bytes
from mcrs_benchmarks.harness import Figure, Goal, Report, make_parser, require_at_least, run_benchmark
from mcrs_benchmarks.memory_anchors import anchors, reference_lookups

from mcrs.env.config import SCENARIOS, EnvConfig, scenario
from mcrs.env.core import MCRSCore
from mcrs.experiment.config import MemoryConfig
from mcrs.memory.codec import StateCodec
from mcrs.memory.delta import DELTA_RULES, match_tolerance
from mcrs.memory.episodic import EpisodicMemory
from mcrs.memory.index import RECENT_MIN, RECENT_SHARE, SHAPES

GOAL_MAP = "map20"
GOAL_ENTRIES = 1_000_000
GOAL_EPISODES = 32
GOAL_LOOKUPS = 3200
GOAL_LOOKUP_MS = 20.0
GOAL_INSERT_MS = 50.0
GOAL_REEMBED_S = 10.0
GOAL_GIB = 1.5
GIB = 2**30
EXTRA_READS = 8  # readings added to random cells of each synthetic state
FILLS = ("synthetic", "algorithm1")
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


def fill_by_algorithm1(memory: EpisodicMemory, config: EnvConfig, transitions: int, seed: int) -> None:
    """Insert ``transitions`` transitions of rolled-out episodes (``FILL_EPISODES`` at a time) through
    Algorithm 1, as a run does: entries merge, so the buffer holds fewer (the density a run sees)."""
    per_batch = FILL_EPISODES * config.max_steps
    for i in range(-(-transitions // per_batch)):
        episodes = min(FILL_EPISODES, -(-(transitions - i * per_batch) // config.max_steps))
        memory.insert(*rollout(config, episodes, seed + i))


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


def upkeep(memory: EpisodicMemory, added: int, report: Report) -> str:
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
    amortised = report.figure(
        "upkeep_ms_per_insertion", (merge_s / every_merge + rebuild_s / every_rebuild) * 1e3, "ms"
    )
    report.figure("upkeep_merge_ms", merge_s * 1e3, "ms", note=f"every ~{every_merge:.0f} insertions")
    report.figure("upkeep_rebuild_s", rebuild_s, "s", note=f"every ~{every_rebuild:.0f} insertions")
    return (
        f"index upkeep: merging recent records {merge_s * 1e3:.1f} ms every ~{every_merge:.0f} insertions, "
        f"purging rebuild {rebuild_s:.2f} s every ~{every_rebuild:.0f}: "
        f"{amortised.value:.1f} ms per insertion amortised"
    )


def _parser() -> argparse.ArgumentParser:
    parser = make_parser(
        "mcrs-bench-memory",
        "Insertion, look-up, re-embedding and size of the episodic memory D_E, with goals.",
    )
    parser.add_argument(
        "--entries",
        type=int,
        default=GOAL_ENTRIES,
        help="entries (synthetic fill) or transitions (algorithm1)",
    )
    parser.add_argument(
        "--fill", choices=FILLS, default=FILLS[0], help="synthetic near-copies (worst case) or Algorithm 1"
    )
    parser.add_argument("--map", choices=SCENARIOS, default=GOAL_MAP, help="env preset")
    parser.add_argument("--episodes", type=int, default=GOAL_EPISODES, help="episodes per inserted batch")
    parser.add_argument("--lookups", type=int, default=GOAL_LOOKUPS, help="keys per timed look-up")
    parser.add_argument("--repeats", type=int, default=5, help="timed repetitions (median) of insert/look-up")
    parser.add_argument("--chunk", type=int, default=4096, help="states per chunk when re-embedding")
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
    return parser


def _validate(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    if not args.delta > 0:
        parser.error(f"--delta must be > 0, got {args.delta}")
    require_at_least(parser, args, 1, "entries", "episodes", "lookups", "repeats", "chunk")


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark, print the figures and the goals, and write them as JSON."""
    return run_benchmark(_parser(), argv, _run, _validate)


def _run(args: argparse.Namespace, report: Report) -> None:
    from mcrs.models.embeddings import make_embedding

    config = scenario(args.map)
    sizes = (args.entries, args.map, args.episodes, args.lookups)
    judged = sizes == (GOAL_ENTRIES, GOAL_MAP, GOAL_EPISODES, GOAL_LOOKUPS) and args.fill == "synthetic"
    not_judged = "" if judged else "goal sizes only: 1M synthetic map20 entries, 32 episodes, 3,200 keys"
    synthetic = args.fill == "synthetic"
    transitions = args.episodes * config.max_steps
    tolerance = match_tolerance(args.delta, args.delta_rule, args.neighbourhood, 4)
    report.header("episodic-memory benchmark")
    print(
        f"{args.map}: state {config.state_dim} floats, T={config.max_steps}; "
        f"{args.entries:,} {'entries (synthetic fill)' if synthetic else 'transitions through Algorithm 1'}, "
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
        tolerance=tolerance,
        max_steps=config.max_steps,
        shape=args.neighbourhood,
    )
    start = time.perf_counter()
    (fill if synthetic else fill_by_algorithm1)(memory, config, args.entries, seed=1)
    fill_s = time.perf_counter() - start
    report.figure("fill_s", fill_s, "s")
    report.figure("entries", len(memory), "entries")

    def judge(name: str, value: float, unit: str, goal: Goal, note: str = "", valid: bool = True) -> Figure:
        """A figure with a goal, judged at the goal sizes only."""
        return report.figure(name, value, unit, goal, not_judged=not_judged, valid=valid, note=note)

    # Re-embedding: every stored state decoded, embedded, and the index rebuilt.
    start, start_cpu = time.perf_counter(), time.process_time()
    memory.refresh_keys(chunk=args.chunk)
    reembed_s, reembed_cpu = time.perf_counter() - start, time.process_time() - start_cpu
    reembed = judge("reembed_s", reembed_s, "s", Goal("<=", GOAL_REEMBED_S), "wall clock")
    reembed_c = judge("reembed_cpu_s", reembed_cpu, "s", Goal("<=", GOAL_REEMBED_S), "process CPU time")
    report.figure("reembed_us_per_state", reembed_s / len(memory) * 1e6, "us")
    print(
        f"\nfill ({'synthetic states written to the storage' if synthetic else 'Algorithm 1'}): "
        f"{fill_s:.2f} s, {len(memory):,} entries\n"
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
    insert = judge("insert_ms", insert_s * 1e3, "ms", Goal("<=", GOAL_INSERT_MS), "wall clock")
    insert_c = judge("insert_cpu_ms", insert_cpu * 1e3, "ms", Goal("<=", GOAL_INSERT_MS), "process CPU time")
    report.figure("insert_embed_ms", embed_s * 1e3, "ms", note="of which the CNN keys")
    for name in ("new", "hits", "shifted", "evicted"):
        report.figure(f"last_batch.{name}", int(getattr(stats, name)), "transitions")
    print(
        f"insert {transitions:,} transitions: {insert_s * 1e3:.2f} ms (of which the CNN keys "
        f"{embed_s * 1e3:.2f} ms; cpu {insert_cpu * 1e3:.2f} ms); last batch: {stats.new} new, "
        f"{stats.hits} hits, {stats.shifted} shifts, {stats.evicted} evicted",
        flush=True,
    )
    print(upkeep(memory, stats.new + stats.shifted, report), flush=True)

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
    near_mean = float(near.mean()) if near.numel() else 0.0
    near_median = float(near.median()) if near.numel() else 0.0
    label, build_s, loop_s, ref_found = reference_lookups(memory, keys)
    agree = int((ref_found == found).sum())
    n = len(keys)
    lookup = judge("lookup_ms", lookup_s * 1e3, "ms", Goal("<=", GOAL_LOOKUP_MS), "wall clock")
    lookup_c = judge("lookup_cpu_ms", lookup_cpu * 1e3, "ms", Goal("<=", GOAL_LOOKUP_MS), "process CPU time")
    report.figure("lookup_hits", int(hit.sum()), "keys", note=f"of {n}")
    report.figure("near_mean", near_mean, "entries", note="within the tolerance of a key that hits")
    report.figure("near_median", near_median, "entries", note="within the tolerance of a key that hits")
    report.figure("reference_build_s", build_s, "s", note=label)
    report.figure("reference_ms", loop_s * 1e3, "ms", note=label)
    report.figure("reference_same_entries", agree, "keys", Goal(">=", n))
    ratio = report.figure("ratio", loop_s / lookup_s, "x", note=f"{label} / ours", valid=agree == n)
    print(
        f"look-up {n:,} keys: {lookup_s * 1e3:.2f} ms ({int(hit.sum()):,} hits; cpu "
        f"{lookup_cpu * 1e3:.2f} ms); entries within the tolerance of a key that hits: mean "
        f"{near_mean:.1f}, median {near_median:.0f}\n"
        f"reference ({label}): build {build_s:.2f} s, "
        f"queries {loop_s * 1e3:.1f} ms; ratio reference / ours = {ratio.value:.1f}x; "
        f"same entries found: {agree:,} of {n:,}",
        flush=True,
    )
    anchors(memory, keys, found, lookup_s, report)

    gc.collect()
    rss_after = resident_bytes()
    rss_gib = None if rss_before is None or rss_after is None else (rss_after - rss_before) / GIB
    report.figure("rss_growth_gib", rss_gib, "GiB", note="process resident memory growth")
    nbytes = memory.nbytes()
    size = judge("buffer_gib", nbytes / GIB, "GiB", Goal("<=", GOAL_GIB), "nbytes")
    rss = "n/a" if rss_gib is None else f"{rss_gib:.3f} GiB"
    print(f"buffer: {size.value:.3f} GiB held (nbytes); process resident memory growth {rss}", flush=True)

    if not judged:
        print(
            "\ngoals: not judged (they apply to --entries 1000000 --map map20 --episodes 32 --lookups 3200 "
            "with the synthetic fill, the worst case)"
        )
        return
    lines = [
        f"look-up of {GOAL_LOOKUPS:,} keys at 1M entries <= {GOAL_LOOKUP_MS:g} ms: {lookup.value:.2f} ms "
        f"{lookup.verdict} (cpu {lookup_c.value:.2f} ms {lookup_c.verdict})",
        f"insertion of {transitions:,} transitions <= {GOAL_INSERT_MS:g} ms: {insert.value:.2f} ms "
        f"{insert.verdict} (cpu {insert_c.value:.2f} ms {insert_c.verdict})",
        f"re-embedding 1M {GOAL_MAP} states (CNN) <= {GOAL_REEMBED_S:g} s: {reembed.value:.2f} s "
        f"{reembed.verdict} (cpu {reembed_c.value:.2f} s {reembed_c.verdict})",
        f"buffer <= {GOAL_GIB:g} GiB: {size.value:.3f} GiB {size.verdict}",
    ]
    print(
        f"\ngoals (wall clock; in brackets the process CPU time, what a quiet machine's wall clock comes "
        f"close to when the load average {load_average()} is above the {os.cpu_count()} cores):\n  "
        + "\n  ".join(lines),
        flush=True,
    )


if __name__ == "__main__":
    raise SystemExit(main())
