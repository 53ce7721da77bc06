"""The training runs' part of ``mcrs-report``: the learning curves with the heuristics as lines, the final
table, the rewards at milestones and table 4, every learner against every heuristic, the paper's claims and
Q_tot (figures 6-8, 10-12)."""

from __future__ import annotations

from mcrs.experiment.util.tables import markdown, mean_std, write_csv
from mcrs.viz.learning_curves import CURVE_METRICS, FINAL_METRICS, Curve, Reference, plot_curves
from mcrs_lab.analysis.claims import CLAIM_Q_TOT, claims_table
from mcrs_lab.analysis.curves import Q_TOT, aggregate, final_rows, milestone_steps, milestone_values
from mcrs_lab.analysis.evaluations import Layout, heuristic_references, heuristic_rows, training_layout
from mcrs_lab.analysis.report_document import Report
from mcrs_lab.analysis.runs import Skipped, TrainingRun, default_labels, label_fields, run_labels
from mcrs_lab.analysis.step_notation import format_steps, seeds_reached, step_labels
from mcrs_lab.analysis.sweep_figure import SWEPT_SETTINGS, plot_sweep, sweep_panels, sweep_points, sweep_table
from mcrs_lab.analysis.table4 import PAPER_TABLE4_ENV, Table4Row, table4
from mcrs_lab.analysis.versus import Versus, versus, versus_table

#: Row order of tables and legends: the paper's baselines first, its method last.
ALGO_ORDER = ("qmix", "vdn", "qplex", "emc", "emu", "emu_370", "emu_change", "semu", "cnn_semu")


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


def final_table(rows: list[dict[str, object]]) -> str:
    """Markdown of ``final_rows``/``heuristic_rows``: method, seeds, env steps, ``mean ± std`` per metric."""
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
    final_md = final_table(rows)
    (report.out / "final.md").write_text(final_md + "\n")
    report.add(
        "Learning curves and final evaluation",
        f"![learning curves]({png.name})\n\n{_references_caption(references)}At the last common "
        f"evaluation step of each method (mean ± std over seeds; heuristics: over evaluation seeds):"
        f"\n\n{final_md}",
    )
    _report_milestones(report, groups, panels["episode reward"], order)
    budget = max(int(c.steps[-1]) for c in panels["episode reward"].values())
    layouts = {label: _layouts(members) for label, members in groups.items()}
    report_versus(
        report,
        versus(finals, order, runs.evaluations, comm_range, budget, layouts),
        "Learners against the heuristics (last tenth of the budget, p < 0.05: one-sample against the "
        "heuristic's score on the learners' episodes, Welch where it played others)",
    )
    _report_sweeps(report, groups, panels["episode reward"], budget)
    q_tot = aggregate(groups, Q_TOT, [])
    if report.claims:
        by_name = {metric.split("/")[-1]: curves for metric, curves in finals.items()}
        by_name[CLAIM_Q_TOT] = q_tot  # figure 8b's claim is on the mean Q_tot (a training scalar)
        aliases = default_labels(runs.training)
        md = claims_table(
            report.claims, by_name, runs.evaluations, comm_range, budget, aliases=aliases, layouts=layouts
        )
        (report.out / "claims.md").write_text(md + "\n")
        report.add("The paper's claims, checked", md)
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


def _report_sweeps(
    report: Report, groups: dict[str, list[TrainingRun]], curves: dict[str, Curve], budget: int
) -> None:
    """For each swept setting with two values or more of one algorithm: <symbol>.png|md, the reward at the
    end against the value (figures 10 and 11), and <symbol>_curves.png, the reward over training at each
    value, a panel per algorithm (figure 12, and figure 10's curves)."""
    for setting, symbol in SWEPT_SETTINGS.items():
        points = sweep_points(groups, curves, budget, setting)
        if not points:
            continue
        md = sweep_table(points, symbol)
        (report.out / f"{symbol}.md").write_text(md + "\n")
        png = plot_sweep(
            points,
            symbol,
            report.out / f"{symbol}.png",
            f"{report.env_name}: episode reward against {symbol}",
        )
        swept = {p.algo for p in points}
        algos = [a for a in ALGO_ORDER if a in swept] + sorted(swept - set(ALGO_ORDER))
        panels, order = sweep_panels(groups, curves, setting, symbol, algos)
        curves_png = plot_curves(
            panels,
            report.out / f"{symbol}_curves.png",
            f"{report.env_name}: episode reward at each {symbol}",
            order,
            panel_legends=True,
        )
        report.add(
            f"Episode reward against {symbol}",
            f"![{symbol}]({png.name})\n\n{md}\n\n![{symbol}, over training]({curves_png.name})",
        )


def _layouts(runs: list[TrainingRun]) -> frozenset[Layout]:
    """The episodes a method's periodic evaluations played; empty where a run's config does not say."""
    found = [training_layout(run.config) for run in runs]
    return frozenset() if None in found else frozenset(found)


def report_versus(report: Report, results: list[Versus], title: str) -> None:
    """versus.md|csv, when there are learners and heuristics to set against each other."""
    if results:
        rows, md = versus_table(results)
        write_csv(report.out / "versus.csv", rows)
        (report.out / "versus.md").write_text(md + "\n")
        report.add(title, md)


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
                seeds_reached(rewards[label].seeds, int(rewards[label].steps[-1]), values),
                *(mean_std(m, sd, n=rewards[label].seeds, missing="-") for m, sd in values),
            ]
        )
    write_csv(report.out / "milestones.csv", rows)
    md = markdown(["method", "seeds", *step_labels(steps)], table)
    (report.out / "milestones.md").write_text(md + "\n")
    when = "thirds of the budget" if report.milestones is None else "the chosen env steps (--milestones)"
    report.add(f"Episode reward at {when}", md)

    # Table 4 where delta was swept, and on the paper's map wherever a memory method ran: there the
    # paper's numbers stand beside ours even at the default delta alone.
    swept = any(
        "algo.memory.delta" in f for f in label_fields([r for g in groups.values() for r in g]).values()
    )
    ours = []
    for label in order:
        first = groups[label][0]
        delta = first.setting("algo.memory.delta")
        if delta is None or not first.setting("algo.memory.enabled"):
            continue  # delta means nothing without a memory (QMIX's config still carries the default)
        values = milestone_values(rewards[label], steps)
        last = int(rewards[label].steps[-1])
        ours.append(Table4Row(delta, first.algo_name, rewards[label].seeds, values, last))
    if not ours or not (swept or report.env_name == PAPER_TABLE4_ENV):
        return
    rows4, md4 = table4(ours, steps, report.env_name)
    write_csv(report.out / "table4.csv", rows4)
    (report.out / "table4.md").write_text(md4 + "\n")
    report.add(
        "Table 4: episode reward by delta (mean ± std over seeds; the paper's beside ours on map20)", md4
    )
