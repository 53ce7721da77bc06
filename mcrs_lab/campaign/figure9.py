"""Figure 9 of a campaign (the t-SNE of states from a run's episodic memory), kept as records.

The runner prunes a finished run's episodic memory out of its ``last.pt``, so the states are drawn
before: a ``tsne:`` entry of the campaign file names the run whose memory D_E is sampled (``memory``: an
algorithm of figure ``of``, on map ``env``, at training seed ``seed``) and the runs whose trained
embeddings key those states (``embeddings``: algorithms of the same figure, map and seed). Two records go
under ``<records>/<entry>/<map>/``:

- ``states.npz``: ``samples`` entries drawn from the memory run's D_E (their compact codes, time and
  return H), written when that run finishes, before its memory is pruned;
- ``tsne.npz``: the 2-D t-SNE of the raw states, of EMC's random projection (seeded with the training
  seed, as an EMC run of that seed projects) and of each embedding's keys, with H and the return-locality
  scores, written once the states are recorded and every embedding run has finished (a pruned
  ``last.pt`` keeps its embedding). ``mcrs-report <records>/<entry>`` draws figure 9 from it alone.

``mcrs-campaign run`` does both as the runs finish; ``mcrs-campaign tsne`` does what the finished runs
allow (the states only while the memory run's ``last.pt`` still holds its memory).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.util.untrusted import UntrustedInput, read_yaml
from mcrs_lab.analysis import tsne
from mcrs_lab.analysis.records import git_facts, machine_facts
from mcrs_lab.analysis.runs import TrainingRun, read_record
from mcrs_lab.campaign.matrix import MAX_SEED, MatrixError, Point, figure_option, load_campaign_file, plain

TSNE_KEYS = {"title", "of", "env", "seed", "memory", "embeddings", "samples"}
STATES = "states.npz"
TSNE = "tsne.npz"
#: At most this many states: the t-SNE of each panel is quadratic in memory beyond it.
MAX_SAMPLES = 100_000


@dataclass(frozen=True)
class TsneEntry:
    """One ``tsne:`` entry of the campaign file, its points resolved."""

    name: str
    title: str
    env: str
    seed: int
    samples: int
    memory: Point  # whose D_E is sampled
    embeddings: tuple[Point, ...]  # whose trained embeddings key the states

    def folder(self, records: Path) -> Path:
        return records / self.name / self.env

    def states_path(self, records: Path) -> Path:
        return self.folder(records) / STATES

    def tsne_path(self, records: Path) -> Path:
        return self.folder(records) / TSNE


def load_tsne(path: Path, points: list[Point]) -> list[TsneEntry]:
    """The ``tsne:`` entries of the campaign file ``path`` (none: an empty list), each refused in one
    line naming the field where it does not fit the file's ``points``."""
    spec = load_campaign_file(path).get("tsne") or {}
    if not isinstance(spec, dict):
        raise MatrixError(f"{path}: tsne: a mapping of names to entries")
    figures = {f for p in points for f in p.figures}
    out = []
    for name, entry in spec.items():
        where = f"{path}: tsne {name}"
        plain(name, f"{path}: tsne name")  # it names a folder of the records
        if not isinstance(entry, dict):
            raise MatrixError(f"{where}: a mapping with keys {sorted(TSNE_KEYS)}")
        unknown = set(entry) - TSNE_KEYS
        if unknown:
            raise MatrixError(f"{where}: unknown keys {sorted(unknown)}; allowed: {sorted(TSNE_KEYS)}")
        missing = sorted({"of", "env", "seed", "memory", "embeddings"} - set(entry))
        if missing:
            raise MatrixError(f"{where}: missing keys {missing}")
        of = entry["of"]
        if not isinstance(of, str) or of not in figures:
            raise MatrixError(f"{where}: of={of!r}: name a figure of the file ({', '.join(sorted(figures))})")
        env = figure_option("env", entry["env"], where)
        seed = entry["seed"]
        if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_SEED:
            raise MatrixError(f"{where}: seed={seed!r}: a whole number in [0, 2**63 - 1]")
        samples = entry.get("samples", 20_000)
        if isinstance(samples, bool) or not isinstance(samples, int) or not 2 <= samples <= MAX_SAMPLES:
            raise MatrixError(f"{where}: samples={samples!r}: a whole number in [2, {MAX_SAMPLES}]")
        embeddings = entry["embeddings"]
        if not isinstance(embeddings, list) or not embeddings:
            raise MatrixError(
                f"{where}: embeddings={embeddings!r}: a list of algorithms, e.g. [semu, cnn_semu]"
            )

        out.append(
            TsneEntry(
                name=str(name),
                title=str(entry.get("title", name)),
                env=env,
                seed=seed,
                samples=samples,
                memory=_point(points, of, env, seed, entry["memory"], f"{where}: memory"),
                embeddings=tuple(
                    _point(points, of, env, seed, a, f"{where}: embeddings") for a in embeddings
                ),
            )
        )
    return out


def _point(points: list[Point], of: str, env: str, seed: int, algo: Any, where: str) -> Point:
    """The point of figure ``of`` with no swept value on ``env`` of ``algo`` at ``seed``."""
    algo = figure_option("algo", algo, where)
    for p in points:
        if of in p.figures and p.env == env and p.algo == algo and p.seed == seed and not p.settings:
            return p
    raise MatrixError(f"{where}={algo!r}: figure {of} has no {env} {algo} point at seed {seed}")


def _finished_run(point: Point, outputs: Path, records: Path) -> Path | None:
    """The run directory of a finished point with its ``last.pt`` here (its own under ``outputs``, else
    the one its record names), or None."""
    record_path = point.record_path(records)
    record = read_record(record_path) if record_path.is_file() else None
    if record is None or record.get("status") != "finished":
        return None
    for run_dir in (point.run_dir(outputs), Path(record["run_dir"])):
        if ckpt.checkpoint_path(run_dir).is_file():
            return run_dir
    return None


def _training_run(run_dir: Path) -> TrainingRun:
    try:
        config = read_yaml(run_dir / "config.yaml", interpolations=False)
    except UntrustedInput as error:
        raise tsne.TsneRecordError(str(error)) from None
    if not isinstance(config, dict) or not all(k in config for k in ("env", "algo", "seed")):
        raise tsne.TsneRecordError(f"{run_dir}: config.yaml is not an mcrs-train config")
    return TrainingRun(run_dir, ckpt.current_config(config))


def _provenance() -> dict[str, Any]:
    return {"git": git_facts(), "machine": machine_facts()}


def sample_states(entry: TsneEntry, run_dir: Path, records: Path) -> str:
    """Draw the entry's states from the memory run's saved D_E into ``states.npz``; the line to print."""
    run = _training_run(run_dir)
    codes = tsne.sample_codes(run, entry.samples, entry.seed)
    path = entry.states_path(records)
    meta = {
        "format": tsne.STATES_FORMAT,
        "version": tsne.TSNE_VERSION,
        "entry": entry.name,
        "run": entry.memory.id,
        "run_dir": str(run_dir),
        "algo": run.algo_name,
        "env": run.config["env"],
        "seed": entry.seed,
        "memory_size": codes["size"],
        "recorded": _provenance(),
    }
    arrays = {k: codes[k].numpy() for k in ("codes", "positions", "step", "returns")}
    tsne.write_npz_record(path, arrays, meta)
    n, size = len(arrays["returns"]), codes["size"]
    return f"tsne {entry.name}: {n} of {size} states of {entry.memory.id}'s memory: {path}"


def make_tsne(entry: TsneEntry, embedding_dirs: list[Path], records: Path) -> str:
    """The t-SNE record from the recorded states and the embedding runs; the line to print."""
    arrays, meta = tsne.read_npz_record(entry.states_path(records), tsne.STATES_FORMAT)
    source = TrainingRun(
        Path(meta["run_dir"]), {"env": meta["env"], "algo": {"name": meta["algo"]}, "seed": entry.seed}
    )
    sample = tsne.decode_sample(source, arrays, meta["env"])
    runs = [_training_run(d) for d in embedding_dirs]
    key_dim = int(runs[0].config["algo"]["memory"]["key_dim"])
    features = {
        "raw state": sample.state,
        "random projection (EMC)": tsne.random_projection_keys(sample, key_dim=key_dim, seed=entry.seed),
    }
    for point, run in zip(entry.embeddings, runs, strict=True):
        features[f"{point.algo} keys"] = tsne.trained_embedding_keys(run, sample)
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):  # beside the campaign's runs, one core at a time each
        out, panels = tsne.tsne_record(features, arrays["returns"], entry.seed)
    tsne_meta = {
        "format": tsne.TSNE_FORMAT,
        "version": tsne.TSNE_VERSION,
        "entry": entry.name,
        "title": entry.title,
        "env": entry.env,
        "seed": entry.seed,
        "states": {"run": meta["run"], "algo": meta["algo"], "memory_size": meta["memory_size"]},
        "embeddings": {p.algo: p.id for p in entry.embeddings},
        "panels": panels,
        "recorded": _provenance(),
    }
    path = entry.tsne_path(records)
    tsne.write_npz_record(path, out, tsne_meta)
    return f"tsne {entry.name}: the t-SNE of {len(out['returns'])} states, {len(panels)} panels: {path}"


def before_prune(entries: list[TsneEntry], point: Point, outputs: Path, records: Path) -> list[str]:
    """For a point that has just finished: its states, where an entry samples its memory and has none
    recorded yet. Called before the run is pruned."""
    lines = []
    for entry in entries:
        if entry.memory != point or entry.states_path(records).is_file():
            continue
        lines.append(_attempt(entry, lambda e=entry: sample_states(e, point.run_dir(outputs), records)))
    return lines


def missing(entries: list[TsneEntry], records: Path) -> list[TsneEntry]:
    """The entries whose t-SNE record is not made yet."""
    return [entry for entry in entries if not entry.tsne_path(records).is_file()]


def pending(entries: list[TsneEntry], outputs: Path, records: Path) -> list[str]:
    """Every t-SNE record that the recorded states and the finished embedding runs allow, and each
    entry's states where its memory run has finished and still holds its memory; the lines to print."""
    lines = []
    for entry in missing(entries, records):
        if not entry.states_path(records).is_file():
            run_dir = _finished_run(entry.memory, outputs, records)
            if run_dir is None:
                lines.append(f"tsne {entry.name}: waits for {entry.memory.id} to finish")
                continue
            lines.append(_attempt(entry, lambda e=entry, d=run_dir: sample_states(e, d, records)))
            if not entry.states_path(records).is_file():
                continue
        dirs = [_finished_run(p, outputs, records) for p in entry.embeddings]
        waiting = [p.id for p, d in zip(entry.embeddings, dirs, strict=True) if d is None]
        if waiting:
            lines.append(f"tsne {entry.name}: waits for {', '.join(waiting)} (finished, its last.pt here)")
            continue
        lines.append(_attempt(entry, lambda e=entry, d=dirs: make_tsne(e, d, records)))
    return lines


def _attempt(entry: TsneEntry, work) -> str:
    try:
        return work()
    except (ValueError, OSError, KeyError, ckpt.CheckpointError) as error:
        text = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        return f"failed: tsne {entry.name}: {text}"


def summary(entries: list[TsneEntry], records: Path) -> list[str]:
    """A line per entry for ``mcrs-campaign status``."""
    lines = []
    for entry in entries:
        if entry.tsne_path(records).is_file():
            state = f"recorded ({entry.tsne_path(records)})"
        elif entry.states_path(records).is_file():
            state = f"states recorded, the t-SNE waits for {', '.join(p.id for p in entry.embeddings)}"
        else:
            state = f"waits for {entry.memory.id}'s memory"
        lines.append(f"tsne {entry.name}: {state}")
    return lines
