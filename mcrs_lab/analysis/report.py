"""``mcrs-report``: figures and tables of the paper's section 6 from run directories.

    mcrs-report outputs/experiments/baselines --out outputs/reports/baselines_map10 --env map10
    mcrs-report outputs/experiments/delta outputs/eval/comm_range --out outputs/reports/delta
    mcrs-report outputs/experiments/baselines --out outputs/reports/tsne --tsne       (figure 9, from saved buffers)
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
- ``milestones.md|csv``: the reward at a third, two thirds and all of the budget; ``table4.md|csv``
  when delta was swept, on map20 with the paper's table 4 beside ours (mcrs_lab.analysis.table4);
- ``versus.md|csv``: every learner against every heuristic on every metric: better, worse or level at
  the end (Welch over seeds) and from which env step it is better (mcrs_lab.analysis.versus);
- ``claims.md``: the paper's claims about this map (``--claims``, default
  ``mcrs_lab/analysis/paper_claims.yaml``) judged on these runs: reproduced, not reproduced, not shown (within
  noise, one seed) or not run (mcrs_lab.analysis.claims); for evaluations only, the claims of ``--claims``;
- ``comm_range.png``, ``comm_range.md|csv``: metrics against R_c (figure 5) from evaluations at
  several ranges, and from training runs that differ in ``env.comm_range``;
- ``tsne.png``, ``tsne.md`` (``--tsne``): figure 9;
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

from mcrs.experiment.checkpoint import CheckpointError
from mcrs.experiment.tables import markdown, mean_std, write_csv
from mcrs.viz.learning_curves import CURVE_METRICS, FINAL_METRICS, Curve, Reference, plot_curves
from mcrs_lab.analysis import comm_range as cr
from mcrs_lab.analysis import tsne
from mcrs_lab.analysis.claims import Claim, ClaimsError, claims_table, default_claims_path, load_claims
from mcrs_lab.analysis.curves import Q_TOT, aggregate, final_rows, milestone_steps, milestone_values
from mcrs_lab.analysis.evaluations import heuristic_references, heuristic_rows, trained_rows
from mcrs_lab.analysis.marl_eval import write_marl_eval
from mcrs_lab.analysis.record_schema import RecordError
from mcrs_lab.analysis.runs import (
    Runs,
    Skipped,
    TrainingRun,
    find_runs,
    label_fields,
    run_labels,
    select_map,
)
from mcrs_lab.analysis.step_notation import format_steps, parse_step_list, step_labels
from mcrs_lab.analysis.table4 import Table4Row, table4
from mcrs_lab.analysis.versus import versus, versus_table

#: Row order of tables and legends: the paper's baselines first, its method last.
ALGO_ORDER = ("qmix", "vdn", "qplex", "emc", "emu", "emu_370", "emu_change", "semu", "cnn_semu")


def milestone_list(text: str) -> list[int]:
    """--milestones' type: :func:`parse_step_list`, its error a usage error naming the option."""
    try:
        return parse_step_list(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


class Report:
    """Collects the sections of ``report.md`` while the figures and tables are written."""

    def __init__(
        self,
        out: Path,
        env_name: str,
        runs: Runs,
        claims: list[Claim] | None = None,
        milestones: list[int] | None = None,
    ) -> None:
        self.out, self.env_name, self.runs = out, env_name, runs
        self.claims = claims or []
        self.milestones = milestones  # env steps of milestones.md (None: thirds of the budget)
        self.sections: list[str] = []
        out.mkdir(parents=True, exist_ok=True)

    def add(self, title: str, body: str) -> None:
        self.sections.append(f"## {title}\n\n{body}\n")
        print(f"\n{title}\n\n{body}", flush=True)

    def write(self) -> Path:
        unique = sorted({(str(s.path), s.reason) for s in self.runs.skipped})
        skipped = "\n".join(f"- `{p}`: {r}" for p, r in unique) or "none"
        n_train, n_eval = len(self.runs.training), len({e.path for e in self.runs.evaluations})
        head = (
            f"# Report: {self.env_name}\n\n{n_train} training runs and {n_eval} evaluation results read; "
            f"{len(unique)} skipped.\n"
        )
        text = "\n".join([head, *self.sections, f"## Skipped\n\n{skipped}\n"])
        path = self.out / "report.md"
        path.write_text(text)
        if unique:
            print(f"\nskipped {len(unique)}:\n{skipped}", flush=True)
        return path


# ------------------------------------------------------------------------------------------ training
def _groups(training: list[TrainingRun]) -> tuple[dict[str, list[TrainingRun]], list[str]]:
    """Runs by method label, and the labels in the paper's algorithm order, then by swept value."""
    labels = run_labels(training)
    fields = label_fields(training)
    groups: dict[str, list[TrainingRun]] = {}
    for run in sorted(training, key=lambda r: str(r.path)):
        groups.setdefault(labels[run.path], []).append(run)

    def order(label: str) -> tuple:
        first = groups[label][0]
        rank = ALGO_ORDER.index(first.algo_name) if first.algo_name in ALGO_ORDER else len(ALGO_ORDER)
        values = tuple(  # numbers before anything else, so that mixed types still sort
            (0, float(v), "") if isinstance(v := first.setting(n), (int, float)) else (1, 0.0, str(v))
            for n in fields[first.algo_name]
        )
        return (rank, first.algo_name, values)

    return groups, sorted(groups, key=order)


def _final_table(rows: list[dict[str, object]]) -> str:
    """Markdown of ``final_rows``/``_heuristic_rows``: method, seeds, env steps, ``mean ± std`` per metric."""
    header = ["method", "seeds", "env steps", *FINAL_METRICS.values()]
    table = []
    for r in rows:
        steps = int(r.get("env_steps", 0))
        cells = [str(r["method"]), str(r.get("seeds", "")), format_steps(steps) if steps else "-"]
        names = [m.split("/")[-1] for m in FINAL_METRICS]
        seeds = int(r["seeds"]) if r.get("seeds") not in (None, "") else None
        table.append(cells + [mean_std(r[f"{n}_mean"], r[f"{n}_std"], n=seeds) for n in names])
    return markdown(header, table)


def _drop_short_seeds(groups: dict[str, list[TrainingRun]], skipped: list[Skipped]) -> None:
    """Leave out of a method the seeds that stopped short of its longest one (a campaign's run stopped
    at a session's end): averaged on the steps every seed logged, one seed stopped at 10k steps would
    hide the finished ones. They are listed as skipped until they are resumed."""
    for label, members in groups.items():
        last = {}
        for run in members:
            found = run.scalar("eval/episode_reward")
            last[run.path] = int(found[0][-1]) if found is not None and len(found[0]) else 0
        longest = max(last.values())
        kept = [run for run in members if last[run.path] >= longest]
        for run in members:
            if last[run.path] < longest:
                skipped.append(
                    Skipped(
                        run.path,
                        f"{label}: stopped at {last[run.path]:,} env steps, short of its "
                        f"method's {longest:,}: left out until it is resumed",
                    )
                )
        groups[label] = kept


def report_training(report: Report) -> dict[str, dict[str, Curve]]:
    runs = report.runs
    groups, order = _groups(runs.training)
    _drop_short_seeds(groups, runs.skipped)
    finals = {m: aggregate(groups, m, runs.skipped if m in CURVE_METRICS else []) for m in FINAL_METRICS}
    panels = {name: finals[metric] for metric, name in CURVE_METRICS.items()}
    order = [label for label in order if label in panels["episode reward"]]
    if not order:
        report.add("Learning curves", "no training run logged eval/episode_reward")
        return {}
    comm_ranges = {r.setting("env.comm_range") for r in runs.training}
    comm_range = comm_ranges.pop() if len(comm_ranges) == 1 else None
    references = heuristic_references(runs.evaluations, comm_range)
    png = plot_curves(
        panels,
        report.out / "learning_curves.png",
        f"{report.env_name}: greedy evaluation",
        order,
        references,
    )

    rows = final_rows(finals, order)
    rows += heuristic_rows(runs.evaluations, comm_range)
    write_csv(report.out / "final.csv", rows)
    final_md = _final_table(rows)
    (report.out / "final.md").write_text(final_md + "\n")
    report.add(
        "Learning curves and final evaluation",
        f"![learning curves]({png.name})\n\n{_references_caption(references)}At the last common "
        f"evaluation step of each method (mean ± std over seeds; heuristics: over evaluation seeds):"
        f"\n\n{final_md}",
    )
    _report_milestones(report, groups, panels["episode reward"], order)
    budget = max(int(c.steps[-1]) for c in panels["episode reward"].values())
    results = versus(finals, order, runs.evaluations, comm_range, budget)
    if results:
        versus_rows, versus_md = versus_table(results)
        write_csv(report.out / "versus.csv", versus_rows)
        (report.out / "versus.md").write_text(versus_md + "\n")
        report.add("Learners against the heuristics (last tenth of the budget, Welch p < 0.05)", versus_md)
    if report.claims:
        by_name = {metric.split("/")[-1]: curves for metric, curves in finals.items()}
        md = claims_table(report.claims, by_name, runs.evaluations, comm_range, budget)
        (report.out / "claims.md").write_text(md + "\n")
        report.add("The paper's claims, checked", md)
    q_tot = aggregate(groups, Q_TOT, [])
    if q_tot:
        png = plot_curves(
            {"mean Q_tot of replayed transitions": q_tot, "episode reward": panels["episode reward"]},
            report.out / "q_tot.png",
            f"{report.env_name}: Q_tot (figure 8b)",
            [label for label in order if label in q_tot],
            references,
        )
        report.add("Mean Q_tot (figure 8b)", f"![Q_tot]({png.name})")
    return panels


def _references_caption(references: dict[str, list[Reference]]) -> str:
    """Which heuristics the figure draws as horizontal lines, or why none (no evaluation of this map)."""
    drawn = {f"{r.label.split(' (')[0]} ({r.count} {r.over})": None for rs in references.values() for r in rs}
    if not drawn:
        return (
            "No heuristic lines: no heuristic evaluation of this map and R_c was given "
            "(`mcrs-eval study=heuristics env=<map>`).\n\n"
        )
    return (
        f"Lines: each method's interquartile mean over seeds with its 95 % stratified bootstrap confidence "
        f"interval. Horizontal lines: the heuristics {', '.join(drawn)}, mean and 95 % band.\n\n"
    )


def _report_milestones(
    report: Report, groups: dict[str, list[TrainingRun]], rewards: dict[str, Curve], order: list[str]
) -> None:
    longest = max((rewards[label] for label in order), key=lambda c: c.steps[-1])
    steps = milestone_steps(longest, at=report.milestones)
    rows, table = [], []
    for label in order:
        values = milestone_values(rewards[label], steps)
        row: dict[str, object] = {"method": label, "seeds": rewards[label].seeds}
        for s, (m, sd) in zip(steps, values, strict=True):
            row[f"reward_{s}_mean"], row[f"reward_{s}_std"] = m, sd
        rows.append(row)
        table.append(
            [
                label,
                str(rewards[label].seeds),
                *(
                    mean_std(row[f"reward_{s}_mean"], row[f"reward_{s}_std"], n=rewards[label].seeds)
                    for s in steps
                ),
            ]
        )
    write_csv(report.out / "milestones.csv", rows)
    md = markdown(["method", "seeds", *step_labels(steps)], table)
    (report.out / "milestones.md").write_text(md + "\n")
    when = "thirds of the budget" if report.milestones is None else "the chosen env steps (--milestones)"
    report.add(f"Episode reward at {when}", md)

    swept = any(
        "algo.memory.delta" in f for f in label_fields([r for g in groups.values() for r in g]).values()
    )
    if not swept:
        return
    ours = []
    for label in order:
        first = groups[label][0]
        delta = first.setting("algo.memory.delta")
        if delta is None or not first.setting("algo.memory.enabled"):
            continue  # delta means nothing without a memory (QMIX's config still carries the default)
        values = milestone_values(rewards[label], steps)
        ours.append(Table4Row(delta, first.algo_name, rewards[label].seeds, values))
    rows4, md4 = table4(ours, steps, report.env_name)
    write_csv(report.out / "table4.csv", rows4)
    (report.out / "table4.md").write_text(md4 + "\n")
    report.add(
        "Table 4: episode reward by delta (mean ± std over seeds; the paper's beside ours on map20)", md4
    )


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
            rows.append(row)
            table.append(
                [label, f"{rc:g}", str(c.seeds[k]), *(f"{c.mean[m][k]:.2f}" for m in cr.RANGE_METRICS)]
            )
    write_csv(report.out / "comm_range.csv", rows)
    md = markdown(["policy", "R_c", "seeds", *cr.RANGE_METRICS.values()], table)
    (report.out / "comm_range.md").write_text(md + "\n")
    report.add("Communication range (figure 5)", f"![communication range]({png.name})\n\n{md}")
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
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.tsne_samples < 2:
        raise SystemExit(f"mcrs-report: error: --tsne-samples={args.tsne_samples}: must be >= 2")
    try:
        runs = find_runs(args.paths)
    except RecordError as error:  # a record or log that fails the schema: named, nothing reported
        raise SystemExit(f"mcrs-report: error: {error}") from None
    if args.marl_eval is not None:  # every map (a task each), before the report keeps one
        data = write_marl_eval(args.marl_eval, runs.training)
        tasks = {task: len(algos) for env in data.values() for task, algos in env.items()}
        print(f"marl-eval JSON: {args.marl_eval} (methods per map: {tasks or 'none'})", flush=True)
    env_name = select_map(runs, args.env)
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
    report = Report(args.out, env_name, runs, claims, args.milestones)
    legacy = Counter(value for run in runs.training for value in run.legacy)
    for value, count in sorted(legacy.items()):  # nothing recorded is reinterpreted: say how it is read
        print(
            f"mcrs-report: {count} run(s) predate {value.split('=')[0]}: read as made ({value})", flush=True
        )
    if runs.training:
        report_training(report)
    has_ranges = report_comm_range(report)
    if args.tsne:
        try:
            report_tsne(report, args.tsne_samples, args.seed)
        except (ValueError, CheckpointError) as error:  # an empty or unreadable buffer: say so, keep the rest
            report.add("t-SNE of memory states (figure 9)", f"not made: {error}")
    if not runs.training and not has_ranges:  # evaluations only: their table
        rows = heuristic_rows(runs.evaluations, None) + trained_rows(runs.evaluations)
        (report.out / "evaluations.md").write_text(_final_table(rows) + "\n")
        report.add(
            "Evaluations",
            "Heuristics: mean ± std over evaluation seeds. Trained policies: each trained run counts by its "
            "mean over its evaluation seeds; mean ± std over the trained runs (seeds = runs).\n\n"
            + _final_table(rows),
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
