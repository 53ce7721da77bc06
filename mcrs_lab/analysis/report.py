"""``mcrs-report``: figures and tables of the paper's section 6 from run directories.

    mcrs-report outputs/experiments/baselines --out outputs/reports/baselines_map10 --env map10
    mcrs-report outputs/experiments/delta outputs/eval/comm_range --out outputs/reports/delta
    mcrs-report outputs/experiments/baselines --out outputs/reports/tsne --tsne       (figure 9, from saved buffers)
    mcrs-report results/records/paper/fig9 --out outputs/reports/fig9                 (figure 9, from its record)
    mcrs-report outputs/experiments/baselines --out outputs/reports/b --marl-eval outputs/reports/b/marl_eval.json

It reads every ``mcrs-train`` run and ``mcrs-eval`` result under the paths (see mcrs_lab.analysis.runs),
keeps one map, groups training runs into methods (an algorithm plus the settings swept within it, e.g.
``cnn_semu lambda=0.5``; the seeds of a method are averaged), and writes into ``--out``:

- ``learning_curves.png``: episode reward, uncertainty, collisions and targets found of the greedy
  evaluations against env steps (figures 6-7, 10, 11-12), IQM over seeds with a 95 % stratified bootstrap
  confidence interval (mcrs_lab.analysis.curves); the heuristics as labelled horizontal lines;
- ``q_tot.png``: the mean Q_tot of replayed transitions (figure 8b);
- ``final.md|csv``: every evaluation metric at the last step, with the heuristics evaluated by
  ``mcrs-eval`` at the same R_c as extra rows;
- ``delta.png|md`` and ``lambda.png|md``: the reward at the end of training against the swept setting
  (figures 11 and 10), and ``delta_curves.png``, ``lambda_curves.png``: the reward over training at each
  value, a panel per algorithm (figure 12, figure 10's curves), when an algorithm ran at two values or more;
- ``milestones.md|csv``: the reward at a third, two thirds and all of the budget; ``table4.md|csv``
  when delta was swept, and on map20 (with the paper's table 4 beside ours) wherever a memory method
  ran (mcrs_lab.analysis.table4);
- ``versus.md|csv``: every learner against every heuristic on every metric: better, worse or level at
  the end (one-sample test against a heuristic's score on the learners' own episodes, Welch over seeds where
  it played others) and from which env step it is better (mcrs_lab.analysis.versus); for
  evaluations only, every trained policy against the heuristics evaluated with it;
- ``claims.md``: the paper's claims about this map (``--claims``, default
  ``mcrs_lab/analysis/paper_claims.yaml``) judged on these runs: reproduced, not reproduced, not shown (within
  noise, one seed) or not run (mcrs_lab.analysis.claims); for evaluations only, the claims of ``--claims``;
- ``comm_range.png``, ``comm_range.md|csv``: metrics against R_c (figure 5) from evaluations at
  several ranges, and from training runs that differ in ``env.comm_range``; ``comm_range_tests.md``:
  figure 5's statement tested on each trained policy evaluated at several ranges (more targets and less
  uncertainty at its largest R_c than at its smallest, paired over its training runs, Holm);
- ``tsne.png``, ``tsne.md``: figure 9, drawn from a t-SNE record (``tsne.npz``, written by a campaign:
  mcrs_lab.campaign.figure9) found under the paths, or with ``--tsne`` computed from saved buffers;
- ``evaluations.md``: when the paths hold evaluations only, the heuristics and trained policies evaluated
  by ``mcrs-eval``;
- ``report.md``: all of it, plus every run that was skipped and why;
- with ``--marl-eval out.json``: every training run's evaluations (all maps) in marl-eval's JSON
  (mcrs_lab.analysis.marl_eval).

Runs logged with any of ``mcrs-train``'s loggers are read: CSV, TensorBoard event files, and wandb runs
(through the CSV history they keep beside them).
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

import numpy as np

from mcrs.experiment.run.checkpoint import CheckpointError
from mcrs.experiment.run.rundir import describe_os_error
from mcrs.experiment.util.tables import markdown, write_csv
from mcrs_lab.analysis import comm_range as cr
from mcrs_lab.analysis import tsne
from mcrs_lab.analysis.claims import ClaimsError, claims_table, default_claims_path, load_claims
from mcrs_lab.analysis.evaluations import heuristic_rows, trained_rows
from mcrs_lab.analysis.marl_eval import write_marl_eval
from mcrs_lab.analysis.record_schema import RecordError
from mcrs_lab.analysis.report_document import Report
from mcrs_lab.analysis.report_training import final_table, report_training, report_versus
from mcrs_lab.analysis.runs import (
    Runs,
    Skipped,
    TrainingRun,
    find_runs,
    select_map,
)
from mcrs_lab.analysis.sensors import sensor_table
from mcrs_lab.analysis.step_notation import parse_step_list
from mcrs_lab.analysis.sweep_figure import SWEPT_SETTINGS
from mcrs_lab.analysis.versus import versus_evaluated

#: Every figure ``mcrs-report`` can draw. Each is drawn only when the records hold what it shows: a
#: document's figure block (mcrs-results) may name one whose records have not landed yet.
FIGURES = (
    "learning_curves.png",
    "q_tot.png",
    "comm_range.png",
    "tsne.png",
    *(f"{symbol}.png" for symbol in SWEPT_SETTINGS.values()),
    *(f"{symbol}_curves.png" for symbol in SWEPT_SETTINGS.values()),
)

TSNE_RECORD = "tsne.npz"


def milestone_list(text: str) -> list[int]:
    """--milestones' type: :func:`parse_step_list`, its error a usage error naming the option."""
    try:
        return parse_step_list(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


# ------------------------------------------------------------------------------------ communication
def report_comm_range(report: Report) -> bool:
    """Figure 5 from whatever varies R_c; False when nothing does."""
    curves = {}
    for label, curve in cr.curves_from_evaluations(report.runs.evaluations).items():
        if len(curve.ranges) > 1:
            curves[f"{label} (evaluated at R_c)"] = curve
    training = report.runs.training
    if len({r.setting("env.comm_range") for r in training}) > 1:
        final: dict[tuple[str, float], dict[str, list[float]]] = {}
        for run in training:
            metrics = final.setdefault((run.algo_name, float(run.setting("env.comm_range"))), {})
            for name in cr.RANGE_METRICS:
                found = run.scalar(f"eval/{name}")
                if found is not None and len(found[1]):
                    metrics.setdefault(name, []).append(float(found[1][-1]))
        curves.update(cr.curves_from_training(final))
    if not curves:
        return False
    png = cr.plot_range_curves(
        curves, report.out / "comm_range.png", f"{report.env_name}: communication range"
    )
    rows, table = [], []
    for label, c in sorted(curves.items()):
        for k, rc in enumerate(c.ranges):
            row = {"policy": label, "comm_range": float(rc), "seeds": int(c.seeds[k])}
            row.update({f"{m}_mean": float(c.mean[m][k]) for m in cr.RANGE_METRICS})
            row.update({f"{m}_std": float(c.std[m][k]) for m in cr.RANGE_METRICS})
            rows.append(row)
            table.append(
                [label, f"{rc:g}", str(c.seeds[k]), *(f"{c.mean[m][k]:.2f}" for m in cr.RANGE_METRICS)]
            )
    write_csv(report.out / "comm_range.csv", rows)
    md = markdown(["policy", "R_c", "seeds", *cr.RANGE_METRICS.values()], table)
    (report.out / "comm_range.md").write_text(md + "\n")
    report.add("Communication range (figure 5)", f"![communication range]({png.name})\n\n{md}")
    tests = cr.range_tests(report.runs.evaluations)
    if tests:
        tests_md = cr.range_tests_table(tests)
        (report.out / "comm_range_tests.md").write_text(tests_md + "\n")
        report.add(
            "Figure 5's statement, tested (largest R_c against the smallest, paired over seeds)", tests_md
        )
    return True


# ---------------------------------------------------------------------------------------------- t-SNE
def _memory_run(training: list[TrainingRun], embedding: str) -> TrainingRun | None:
    runs = [
        r
        for r in training
        if r.setting("algo.memory.enabled")
        and r.setting("algo.memory.embedding") == embedding
        and (r.path / "checkpoints" / "last.pt").is_file()
    ]
    return min(runs, key=lambda r: (r.seed, str(r.path))) if runs else None


def report_tsne(report: Report, samples: int, seed: int) -> None:
    training = report.runs.training
    cnn, fc = _memory_run(training, "cnn"), _memory_run(training, "fc")
    source = cnn or fc or _memory_run(training, "random")
    if source is None:
        report.add("t-SNE of memory states (figure 9)", "not made: no run with a saved episodic memory")
        return
    sample = tsne.sample_memory(source, samples, seed)
    features = {
        "raw state": sample.state,
        "random projection (EMC)": tsne.random_projection_keys(sample, seed=seed),
    }
    for name, run in (("SEMU keys (FC)", fc), ("CNN-SEMU keys", cnn)):
        if run is None:
            report.runs.skipped.append(Skipped(Path(name), "t-SNE panel not made: no such run with last.pt"))
        else:
            features[name] = tsne.trained_embedding_keys(run, sample)
    returns = sample.returns.numpy().astype(np.float64)
    panels, scores, rows = {}, {}, []
    for name, x in features.items():
        x = x.numpy()
        print(f"t-SNE of {len(x)} states: {name} ...", flush=True)
        panels[name] = tsne.tsne_2d(x, seed)
        scores[name] = tsne.return_locality(panels[name], returns, seed)
        in_space = tsne.return_locality(tsne.standardise(x.astype(np.float64)), returns, seed)
        rows.append([name, f"{x.shape[1]}", f"{in_space:.3f}", f"{scores[name]:.3f}"])
    png = tsne.plot_tsne(panels, returns, scores, report.out / "tsne.png")
    md = markdown(
        ["representation", "dims", "return locality (representation)", "return locality (t-SNE)"], rows
    )
    source_text = (
        f"{len(returns)} states drawn from the saved D_E of `{source.path}` ({source.algo_name}); "
        "the same states in every panel. Return locality: mean |H_i - H_j| over the 10 nearest "
        "neighbours / over random pairs (1 = no relation between distance and return)."
    )
    (report.out / "tsne.md").write_text(f"{source_text}\n\n{md}\n")
    report.add("t-SNE of memory states (figure 9)", f"![t-SNE]({png.name})\n\n{source_text}\n\n{md}")


def find_tsne_records(paths: list[Path]) -> list[Path]:
    """The t-SNE records (``tsne.npz``) under ``paths``, each a record or a folder holding them."""
    found: list[Path] = []
    for root in paths:
        if root.is_file() and root.name.endswith(".npz"):
            found.append(root)
        elif root.is_dir():
            found += sorted(p for p in root.rglob(TSNE_RECORD) if p.is_file())
    return list(dict.fromkeys(found))


def report_tsne_record(report: Report, path: Path) -> None:
    """Figure 9 from a t-SNE record alone."""
    arrays, meta = tsne.read_npz_record(path, tsne.TSNE_FORMAT)
    panels = {p["name"]: arrays["xy"][k] for k, p in enumerate(meta["panels"])}
    scores = {p["name"]: float(p["locality_tsne"]) for p in meta["panels"]}
    returns = arrays["returns"].astype(np.float64)
    png = tsne.plot_tsne(panels, returns, scores, report.out / "tsne.png")
    md = tsne.tsne_table(meta["panels"])
    states = meta.get("states") or {}
    embeddings = ", ".join(f"{a}: `{p}`" for a, p in (meta.get("embeddings") or {}).items())
    source_text = (
        f"{len(returns)} states drawn from the D_E of `{states.get('run')}` ({states.get('algo')}, "
        f"{states.get('memory_size')} entries), the same states in every panel; keys of the trained "
        f"embeddings of {embeddings or 'none'}; record `{path}`. Return locality: mean |H_i - H_j| over "
        "the 10 nearest neighbours / over random pairs (1 = no relation between distance and return)."
    )
    (report.out / "tsne.md").write_text(f"{source_text}\n\n{md}\n")
    report.add("t-SNE of memory states (figure 9)", f"![t-SNE]({png.name})\n\n{source_text}\n\n{md}")


def _tsne_records_of(paths: list[Path], env_name: str | None) -> list[tuple[Path, str]]:
    """The t-SNE records under ``paths`` with their map (``env_name``: that map's only)."""
    out = []
    for path in find_tsne_records(paths):
        try:
            _, meta = tsne.read_npz_record(path, tsne.TSNE_FORMAT)
        except tsne.TsneRecordError as error:
            raise SystemExit(f"mcrs-report: error: {error}") from None
        if env_name is None or meta.get("env") == env_name:
            out.append((path, str(meta.get("env"))))
    return out


# ------------------------------------------------------------------------------------------------ CLI
def _section6(runs: Runs) -> bool:
    """Whether the runs come from a section-6 preset (``experiment=``; heuristics alone count: their
    claims are the paper's too), so that the paper's claims table is about them."""
    return not runs.training or any(str(r.setting("experiment") or "none") != "none" for r in runs.training)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mcrs-report",
        description="Figures and tables of the paper's section 6 from mcrs-train runs and mcrs-eval results.",
    )
    parser.add_argument("paths", nargs="+", type=Path, help="run directories, or folders holding runs")
    parser.add_argument(
        "--out", type=Path, required=True, help="folder for the figures, tables and report.md"
    )
    parser.add_argument("--env", default=None, help="the map to report (default: the map with the most runs)")
    parser.add_argument("--tsne", action="store_true", help="also make figure 9 from saved episodic buffers")
    parser.add_argument("--tsne-samples", type=int, default=20_000, help="states in the t-SNE (paper: 20000)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the t-SNE and of its sample")
    parser.add_argument(
        "--claims",
        type=Path,
        default=None,
        metavar="YAML",
        help="the claims to check, per map (default: the paper's, mcrs_lab/analysis/paper_claims.yaml)",
    )
    parser.add_argument(
        "--milestones",
        type=milestone_list,
        default=None,
        metavar="STEPS",
        help="env steps of milestones.md, comma-separated (100k,300k,1M; default: thirds of the budget); "
        "each becomes the nearest step the longest run evaluated at",
    )
    parser.add_argument(
        "--marl-eval",
        type=Path,
        default=None,
        metavar="JSON",
        help="also write the training runs' evaluations (every map) as marl-eval's raw-data JSON",
    )
    parser.add_argument("--force", action="store_true", help="replace the --marl-eval file if it exists")
    return parser


def output_problem(out: Path, marl_eval: Path | None, force: bool) -> str | None:
    """Where the report may not write, said before anything is read or written: ``--out`` must be a
    folder, and ``--marl-eval`` a file that is not there yet (or ``--force``): it may name any path, so a
    run's ``config.yaml`` or a record is never replaced by mistake."""
    if out.exists() and not out.is_dir():
        return f"--out {out}: a file, not a folder: name the folder the report goes into"
    if marl_eval is None:
        return None
    if marl_eval.is_dir():
        return f"--marl-eval {marl_eval}: a folder: name the JSON file to write (e.g. {marl_eval / 'marl_eval.json'})"
    if marl_eval.exists() and not force:
        return f"--marl-eval {marl_eval}: the file exists; pass --force to replace it"
    return None


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.tsne_samples < 2:
        raise SystemExit(f"mcrs-report: error: --tsne-samples={args.tsne_samples}: must be >= 2")
    if not 0 <= args.seed < 2**32:  # numpy's and scikit-learn's seeds
        raise SystemExit(f"mcrs-report: error: --seed={args.seed}: must be in [0, 2**32 - 1]")
    problem = output_problem(args.out, args.marl_eval, args.force)
    if problem:
        raise SystemExit(f"mcrs-report: error: {problem}")
    try:
        return make_report(args)
    except OSError as error:
        # an unwritable --out, a full disk: one line (the marl-eval JSON is whole or absent)
        raise SystemExit(f"mcrs-report: error: {describe_os_error(error)}") from None


def make_report(args: argparse.Namespace) -> int:
    """The report of ``mcrs-report``'s parsed arguments (:func:`main`)."""
    try:
        runs = find_runs(args.paths)
    except RecordError as error:  # a record or log that fails the schema: named, nothing reported
        raise SystemExit(f"mcrs-report: error: {error}") from None
    training_of_every_map = list(runs.training)  # --marl-eval: every map (a task each); the report keeps one
    env_name = select_map(runs, args.env)
    tsne_records = _tsne_records_of(args.paths, args.env or env_name)
    if (env_name is None or (not runs.training and not runs.evaluations)) and tsne_records:
        env_name = tsne_records[0][1]  # a t-SNE record alone: figure 9
        report = Report(args.out, env_name, runs, [], args.milestones)
        for path, env in tsne_records:
            if env == env_name:
                report_tsne_record(report, path)
        print(f"\nreport: {report.write()}", flush=True)
        return 0
    if env_name is None or (not runs.training and not runs.evaluations):
        reasons = "; ".join(sorted({f"{s.path}: {s.reason}" for s in runs.skipped})) or "none found"
        where = f"map {args.env}" if args.env else "the paths"
        raise SystemExit(f"mcrs-report: error: no readable runs of {where} ({reasons})")
    try:
        claims = load_claims(args.claims or default_claims_path(), env_name)
    except ClaimsError as error:
        raise SystemExit(f"mcrs-report: error: --claims: {error}") from None
    if args.claims is None and not _section6(runs):  # a plain sweep is not the paper's figure: no table of
        claims = []  # "not run" rows; --claims asks for one anyway
    if args.marl_eval is not None:  # once every input has been read and checked
        data = write_marl_eval(args.marl_eval, training_of_every_map)
        tasks = {task: len(algos) for env in data.values() for task, algos in env.items()}
        print(f"marl-eval JSON: {args.marl_eval} (methods per map: {tasks or 'none'})", flush=True)
    report = Report(args.out, env_name, runs, claims, args.milestones)
    legacy = Counter(value for run in runs.training for value in run.legacy)
    for value, count in sorted(legacy.items()):  # nothing recorded is reinterpreted: say how it is read
        print(
            f"mcrs-report: {count} run(s) predate {value.split('=')[0]}: read as made ({value})", flush=True
        )
    if runs.training:
        report_training(report)
    has_ranges = report_comm_range(report)
    sensors = sensor_table(runs.evaluations, env_name)
    if sensors is not None:
        (report.out / "sensors.md").write_text(sensors + "\n")
        report.add("The heuristics and the bound by sensor model", sensors)
    for path, env in tsne_records:
        if env == env_name:
            report_tsne_record(report, path)
    if args.tsne and not tsne_records:
        try:
            report_tsne(report, args.tsne_samples, args.seed)
        except (ValueError, CheckpointError) as error:  # an empty or unreadable buffer: say so, keep the rest
            report.add("t-SNE of memory states (figure 9)", f"not made: {error}")
    if not runs.training and not has_ranges:  # evaluations only: their table
        rows = heuristic_rows(runs.evaluations, None) + trained_rows(runs.evaluations)
        (report.out / "evaluations.md").write_text(final_table(rows) + "\n")
        report.add(
            "Evaluations",
            "Heuristics: mean ± std over evaluation seeds. Trained policies: each trained run counts by its "
            "mean over its evaluation seeds; mean ± std over the trained runs (seeds = runs).\n\n"
            + final_table(rows),
        )
        report_versus(
            report,
            versus_evaluated(runs.evaluations),
            "Trained policies against the heuristics (each trained run one sample, p < 0.05: one-sample "
            "against the heuristic's score on the same episodes, Welch where it played others)",
        )
        if report.claims and args.claims is not None:  # the paper's claims are about training curves
            md = claims_table(report.claims, {}, runs.evaluations, None, 0, "on the same fixed episodes")
            (report.out / "claims.md").write_text(md + "\n")
            report.add("The claims, checked", md)
    path = report.write()
    print(f"\nreport: {path}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
