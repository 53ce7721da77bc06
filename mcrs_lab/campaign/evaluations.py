"""Evaluations of the campaign's finished policies (``mcrs-campaign evaluate``).

A question asked of trained policies after training, such as "does the no-fly shield at test time make
a learner beat the greedy heuristic?", is a named entry under ``evaluations:`` of the campaign file: the
figures whose finished points it evaluates (``algo``: only these algorithms' points), the heuristics
evaluated beside them, the episodes and evaluation seeds, and its variants (each a list of ``mcrs-eval``
overrides). With ``trained: false`` only the heuristics run, on the maps of those figures: at
``seeds: [1000000]`` and ``episodes: 32`` they play the episodes every learner's periodic evaluation plays
during training (``train.eval_seed`` and ``train.eval_episodes``), so a learner and a heuristic are
compared on the same layouts. Each (variant, policy) is
one ``mcrs-eval -m`` over the seeds on the point's map; each seed's result is recorded under

    <records>/<evaluation>/<variant>/eval/<map>/<policy>_rc<R_c>_seed<k>.json

(mcrs_lab.analysis.records.evaluation_record_path), so what is already recorded is skipped and the committed
records alone make the evaluation's tables (``mcrs-report <records>/<evaluation>/<variant>/eval/<map>``).
"""

from __future__ import annotations

import os
import shlex
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.schema import MAX_EVAL_EPISODES
from mcrs.experiment.util.untrusted import UntrustedInput, confined
from mcrs_lab.analysis.records import (
    RecordError,
    evaluation_record_name,
    make_record,
    trained_policy_name,
    write_record,
)
from mcrs_lab.analysis.runs import is_heuristic_policy, read_record
from mcrs_lab.campaign.matrix import (
    MAX_SEED,
    MatrixError,
    Point,
    check_overrides,
    figure_option,
    load_campaign_file,
    plain,
)

EVALUATION_KEYS = {"title", "of", "algo", "heuristics", "episodes", "seeds", "variants", "trained"}
#: What ``EvaluationJob.command`` sets for each job: a variant's overrides may not.
EVAL_KEYS = ("policy", "env", "episodes", "seed", "figures")


@dataclass(frozen=True)
class Evaluation:
    """One ``evaluations:`` entry of the campaign file."""

    name: str
    title: str
    of: tuple[str, ...]  # figures whose finished points are evaluated
    heuristics: tuple[str, ...]
    episodes: int
    seeds: tuple[int, ...]
    variants: tuple[tuple[str, tuple[str, ...]], ...]  # (variant, its mcrs-eval overrides)
    algos: tuple[str, ...] = ()  # only these algorithms' points (empty: every algorithm of the figures)
    trained: bool = True  # False: the heuristics alone, on the maps of the figures in ``of``

    def evaluates(self, point: Point) -> bool:
        """Whether ``point`` is one of the finished policies this evaluation asks for."""
        return bool(set(point.figures) & set(self.of)) and (not self.algos or point.algo in self.algos)


@dataclass(frozen=True)
class EvaluationJob:
    """One ``mcrs-eval -m`` over an evaluation's seeds: one policy, one variant, one map."""

    evaluation: Evaluation
    variant: str
    overrides: tuple[str, ...]
    env: str
    policy: str  # a heuristic's name or a finished run's directory
    label: str  # the point id, or the heuristic's name
    settings: tuple[str, ...] = ()  # the point's swept env fields: evaluated where it was trained

    def records_dir(self, records: Path) -> Path:
        return records / self.evaluation.name / self.variant

    def recorded(self, records: Path) -> bool:
        """Whether every evaluation seed already has its record (any R_c: the map's own)."""
        folder = self.records_dir(records) / "eval" / self.env
        return all(self._recorded_seed(folder, seed) for seed in self.evaluation.seeds)

    def _recorded_seed(self, folder: Path, seed: int) -> bool:
        if is_heuristic_policy(self.policy):
            return any(folder.glob(evaluation_record_name(self.policy, "*", seed)))
        # A trained policy's records name its run: <label>-<experiment>-<run folder> (self.label is the
        # point id, <experiment>/<run folder>).
        if any(folder.glob(evaluation_record_name(trained_policy_name("*", self.label), "*", seed))):
            return True
        # Records made before the run's experiment was kept name the folder alone; one counts only where
        # its policy path runs through the point's experiment (two experiments' runs share folder names).
        experiment, run = self.label.split("/", 1)
        for path in folder.glob(evaluation_record_name(f"*-{run}", "*", seed)):
            record = read_record(path)
            rows = record.get("rows") if record else None
            if rows and rows[0].get("run") is None and experiment in Path(str(record.get("policy"))).parts:
                return True
        return False

    def sweep_dir(self, outputs: Path) -> Path:
        return outputs / "evaluations" / self.evaluation.name / self.variant / self.label.replace("/", "_")

    def command(self, outputs: Path) -> list[str]:
        seeds = ",".join(str(s) for s in self.evaluation.seeds)
        return [
            sys.executable,
            "-m",
            "mcrs.evaluate",
            "-m",
            f"policy={self.policy}",
            f"env={self.env}",
            *self.settings,
            *self.overrides,
            f"episodes={self.evaluation.episodes}",
            f"seed={seeds}",
            "figures=false",
            f"hydra.sweep.dir={self.sweep_dir(outputs)}",
        ]


def _as_tuple(value: Any) -> tuple[Any, ...]:
    return tuple(value) if isinstance(value, (list, tuple)) else (value,)


def load_evaluations(path: Path, figures: set[str]) -> list[Evaluation]:
    """The ``evaluations:`` entries of the campaign file ``path`` (none: an empty list)."""
    spec = load_campaign_file(path).get("evaluations") or {}
    if not isinstance(spec, dict):
        raise MatrixError(f"{path}: evaluations: a mapping of evaluation names to entries")
    out = []
    for name, entry in spec.items():
        where = f"{path}: evaluation {name}"
        if not isinstance(entry, dict):
            raise MatrixError(f"{where}: a mapping with keys {sorted(EVALUATION_KEYS)}")
        unknown = set(entry) - EVALUATION_KEYS
        if unknown:
            raise MatrixError(f"{where}: unknown keys {sorted(unknown)}; allowed: {sorted(EVALUATION_KEYS)}")
        of = tuple(str(f) for f in _as_tuple(entry.get("of", ())))
        bad = [f for f in of if f not in figures]
        if not of or bad:
            raise MatrixError(
                f"{where}: of={list(of)}: name figures of the file ({', '.join(sorted(figures))})"
            )
        algos = tuple(figure_option("algo", a, where) for a in _as_tuple(entry.get("algo", ())))
        variants = entry.get("variants") or {}
        if not isinstance(variants, dict) or not variants:
            raise MatrixError(
                f'{where}: variants: a mapping of names to mcrs-eval overrides, e.g. {{"on": [...]}}'
            )
        plain(name, f"{path}: evaluation name")  # it names folders under the outputs and the records
        for variant in variants:
            if not isinstance(variant, str):
                raise MatrixError(
                    f"{where}: variant {variant!r}: not a name (YAML reads a bare on/off/yes/no as true/false: "
                    "quote it)"
                )
            plain(variant, f"{where}: variant")
        episodes, seeds = entry.get("episodes", 32), _as_tuple(entry.get("seeds", (0,)))
        if not isinstance(episodes, int) or episodes < 1:
            raise MatrixError(f"{where}: episodes={episodes!r}: a whole number >= 1")
        if isinstance(episodes, bool) or episodes > MAX_EVAL_EPISODES:
            raise MatrixError(f"{where}: episodes={episodes!r}: a whole number in [1, {MAX_EVAL_EPISODES}]")
        if not seeds or not all(
            isinstance(s, int) and not isinstance(s, bool) and 0 <= s <= MAX_SEED for s in seeds
        ):
            raise MatrixError(f"{where}: seeds={list(seeds)}: whole numbers in [0, 2**63 - 1]")
        trained = entry.get("trained", True)
        if not isinstance(trained, bool):
            raise MatrixError(f"{where}: trained={trained!r}: true or false")
        if not trained and not entry.get("heuristics"):
            raise MatrixError(f"{where}: trained: false needs heuristics to evaluate")
        out.append(
            Evaluation(
                name=str(name),
                title=str(entry.get("title", name)),
                of=of,
                heuristics=tuple(_heuristic(h, where) for h in _as_tuple(entry.get("heuristics", ()))),
                episodes=episodes,
                seeds=tuple(seeds),
                variants=tuple(
                    (str(v), check_overrides(ov or (), f"{where}: variant {v}", EVAL_KEYS))
                    for v, ov in variants.items()
                ),
                algos=algos,
                trained=trained,
            )
        )
    return out


def _heuristic(name: Any, where: str) -> str:
    from mcrs.policies import POLICIES

    if name not in POLICIES:
        raise MatrixError(f"{where}: heuristics: {name!r}: allowed values are {', '.join(POLICIES)}")
    return str(name)


def plan(
    evaluations: list[Evaluation], points: list[Point], records: Path, outputs: Path | None = None
) -> tuple[list[EvaluationJob], list[str]]:
    """The jobs for the selected points and each map's heuristics, and a line for each point left out,
    saying why. A point counts once it has a record of a finished run; its run directory is needed only
    for a variant not recorded yet (a fresh clone has the records, not the runs): the point's own under
    ``outputs`` where it has a checkpoint there, else the one its record names (a path relative to where
    the campaign ran)."""
    jobs: list[EvaluationJob] = []
    left_out: list[str] = []
    for evaluation in evaluations:
        chosen = [p for p in points if evaluation.evaluates(p)]
        policies: list[tuple[str, str, str, tuple[str, ...]]] = []  # (map, policy, label, settings)
        for env in dict.fromkeys(p.env for p in chosen):
            # The heuristics share the scenario overrides that every point of the map has (a penalty rule).
            on_map = [{o for o in p.overrides if o.startswith("env.")} for p in chosen if p.env == env]
            shared = tuple(sorted(set.intersection(*on_map)))
            policies += [(env, h, h, shared) for h in evaluation.heuristics]
        for point in chosen if evaluation.trained else ():
            record_path = point.record_path(records)
            record = read_record(record_path) if record_path.is_file() else None
            if record is None or record.get("status") != "finished":
                left_out.append(f"not evaluated: {point.id}: no record of a finished run")
                continue
            settings = tuple(f"{k}={v}" for k, v in point.settings if k.startswith("env."))
            settings += tuple(o for o in point.overrides if o.startswith("env."))
            here = None if outputs is None else str(point.run_dir(outputs))
            run_dir = here if here is not None and _runnable(here) else record["run_dir"]
            policies.append((point.env, run_dir, point.id, settings))
        gone: dict[str, str] = {}  # point id -> its missing run directory, for a variant still to run
        for variant, overrides in evaluation.variants:
            for policy in policies:
                job = EvaluationJob(evaluation, variant, overrides, *policy)
                if job.recorded(records) or is_heuristic_policy(job.policy) or _runnable(job.policy):
                    jobs.append(job)
                else:
                    gone[job.label] = job.policy
        left_out += [f"not evaluated: {p}: its run directory {d} is not here" for p, d in gone.items()]
    return jobs, left_out


def _runnable(run_dir: str) -> bool:
    return ckpt.checkpoint_path(Path(run_dir)).is_file()


def summary(evaluations: list[Evaluation], points: list[Point], records: Path) -> list[str]:
    """A line per evaluation for ``mcrs-campaign status``: how many of its evaluations are recorded."""
    lines = []
    for evaluation in evaluations:
        jobs, left_out = plan([evaluation], points, records)
        if not jobs and not left_out:
            continue  # none of its figures is selected
        done = sum(job.recorded(records) for job in jobs)
        lines.append(
            f"evaluation {evaluation.name}: {done} of {len(jobs)} (policy, variant) evaluations recorded, "
            f"{len(left_out)} points not evaluable yet (mcrs-campaign evaluate --dry-run lists them)"
        )
    return lines


def run_job(job: EvaluationJob, outputs: Path, records: Path) -> list[str]:
    """Run one job and record each seed's result; returns the lines to print. The sweep folder is this
    job's own: an earlier attempt's is replaced."""
    try:  # the names were checked on load; a folder outside the outputs is never removed all the same
        sweep = confined(job.sweep_dir(outputs), outputs, "the evaluation's folder")
    except UntrustedInput as error:
        raise RecordError(str(error)) from None
    if sweep.exists():
        shutil.rmtree(sweep)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "0"}
    done = subprocess.run(job.command(outputs), capture_output=True, text=True, env=env)
    if done.returncode != 0:
        tail = (done.stdout + done.stderr).strip().splitlines()[-5:]
        raise RecordError(f"mcrs-eval exited {done.returncode}:\n  " + "\n  ".join(tail))
    lines = []
    for result in sorted(p.parent for p in sweep.glob("*/metrics.csv")):
        path, record = make_record(result, job.records_dir(records))
        lines.append(f"  {write_record(path, record)} {path}")
    if len(lines) != len(job.evaluation.seeds):
        raise RecordError(f"{sweep}: {len(lines)} results for {len(job.evaluation.seeds)} seeds")
    return lines


def run_pending(
    jobs: list[EvaluationJob], outputs: Path, records: Path, dry_run: bool = False
) -> tuple[int, int]:
    """Run each job not yet recorded, one at a time (a failure is printed, the others still run);
    returns (run, failed). A dry run prints the commands instead."""
    ran = failed = 0
    for job in jobs:
        what = f"{job.evaluation.name}/{job.variant} {job.label}"
        if job.recorded(records):
            continue
        if dry_run:
            print(f"evaluate {what}: {shlex.join(job.command(outputs))}", flush=True)
            continue
        try:
            lines = run_job(job, outputs, records)
        except (RecordError, ckpt.CheckpointError) as error:
            print(f"failed: {what}: {error}", flush=True)
            failed += 1
            continue
        ran += 1
        print(f"evaluated {what}:", *lines, sep="\n", flush=True)
    return ran, failed


def evaluate(
    evaluations: list[Evaluation], points: list[Point], outputs: Path, records: Path, dry_run: bool = False
) -> int:
    """``mcrs-campaign evaluate``: every job of the selected points not yet recorded; 0, or 1 if one
    failed."""
    jobs, left_out = plan(evaluations, points, records, outputs)
    for line in left_out:
        print(line, flush=True)
    for job in jobs:
        if job.recorded(records):
            print(f"recorded: {job.evaluation.name}/{job.variant} {job.label}", flush=True)
    ran, failed = run_pending(jobs, outputs, records, dry_run)
    if not dry_run:
        print(f"evaluations: {ran} run, {failed} failed, {len(left_out)} points not evaluated", flush=True)
    return 1 if failed else 0
