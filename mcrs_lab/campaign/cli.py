"""``mcrs-campaign``: the section-6 campaign (mcrs_lab/campaign/section6_paper.yaml) on one machine.

    mcrs-campaign status [--only fig7]                  which points are done, partial or missing, which training
    mcrs-campaign run --hours 10 --jobs 2 [--only ...]  run the next ones (partial first); --dry-run lists them
    mcrs-campaign run --hours 2.5 --fill                 the same, every slot busy, stopped (resumable) at 2.5 h
    mcrs-campaign run --hours 2.5 --fill --finish-first  the same, the runs that can end by then started first
    mcrs-campaign run --hours 2.5 --fill --finish-only   only those (a machine that does not keep run folders)
    mcrs-campaign run --hours 2 --jobs 1 --threads 2 --only <point>   one slow point on both cores
    mcrs-campaign evaluate [--only fig7] [--dry-run]    the file's evaluations of finished policies
    mcrs-campaign tsne                                  the file's t-SNE records (figure 9) the runs allow
    mcrs-campaign record RUN_DIR... [--prune]           a record of any mcrs-train run or mcrs-eval result
    mcrs-campaign record RUN_DIR --matrix FILE          the same, in that campaign file's records root
    mcrs-campaign report --out DIR [--only fig7]        mcrs-report on the records of the selected points

A campaign file named ``paper`` keeps its records in results/records/paper/ (commit them) and its runs in
outputs/paper/; --records and --outputs say otherwise. See docs/RESULTS.md.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections import Counter
from pathlib import Path

from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.run.rundir import describe_os_error
from mcrs.experiment.util.tables import markdown
from mcrs_lab.analysis.records import RECORDS_DIR, RecordError, make_record, write_record
from mcrs_lab.campaign import figure9
from mcrs_lab.campaign.evaluations import Evaluation, evaluate, load_evaluations, summary
from mcrs_lab.campaign.matrix import (
    DEFAULT_MATRIX,
    MatrixError,
    Point,
    budget_steps,
    campaign_roots,
    load_matrix,
    select,
)
from mcrs_lab.campaign.pace import left_line
from mcrs_lab.campaign.progress import STATES, Progress
from mcrs_lab.campaign.runner import FILL_FLOOR_S, Campaign, CampaignBusy, claim_holder

#: --hours beyond a year is a typo (and time.time() + inf never ends).
MAX_HOURS = 24 * 366


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mcrs-campaign", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)

    def matrix_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("--matrix", type=Path, default=DEFAULT_MATRIX, help="the campaign file")
        p.add_argument(
            "--only",
            action="append",
            default=[],
            help="points to keep: a figure, experiment, map, algorithm, seed<k> or point id (a figure's "
            "name means the figure where an experiment has the same name); comma = or, repeated = and",
        )
        p.add_argument("--outputs", type=Path, help="where the runs go (default: the file's, see above)")
        p.add_argument("--records", type=Path, help="where the records go (default: the file's)")

    status = sub.add_parser(
        "status", help="done, unrecorded, partial or missing, per point, and who trains it now"
    )
    matrix_options(status)
    status.add_argument("--jobs", type=int, default=2, help="runs at a time, for the time left")
    run = sub.add_parser("run", help="run the next points within a time budget")
    matrix_options(run)
    run.add_argument(
        "--hours", type=float, required=True, help="no run starts that would end after this (see --fill)"
    )
    run.add_argument(
        "--fill",
        action="store_true",
        help="keep every slot busy until --hours, then stop the runs still going (each checkpoints and "
        f"is resumed first next time); no start in the last {FILL_FLOOR_S / 60:g} minutes",
    )
    run.add_argument(
        "--finish-first",
        action="store_true",
        help="with --fill: a freed slot takes first the runs expected to end before --hours (partial runs "
        "still resume first), then the rest (for a machine that may not keep its run folders)",
    )
    run.add_argument(
        "--finish-only",
        action="store_true",
        help="with --fill: start only the runs expected to end before --hours (and resume partial ones); "
        "a slot no run can fill in time stays free (a machine that does not keep its run folders would "
        "lose a run stopped at the deadline)",
    )
    run.add_argument("--jobs", type=int, default=2, help="runs at a time (each with one torch thread)")
    run.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch threads of each run (default 1: two 1-thread runs side by side make the most env steps "
        "an hour; one 2-thread run, --jobs 1 --threads 2, ends a slow point sooner)",
    )
    run.add_argument("--dry-run", action="store_true", help="list the commands, run nothing")
    run.add_argument("--keep-replay", action="store_true", help="do not prune finished runs' last.pt")
    run.add_argument(
        "--no-evaluate", action="store_true", help="do not run the file's evaluations of finished runs"
    )
    evaluation = sub.add_parser(
        "evaluate", help="run the campaign file's evaluations of finished policies not yet recorded"
    )
    matrix_options(evaluation)
    evaluation.add_argument(
        "--evaluation", action="append", default=[], help="only these evaluations (default: all)"
    )
    evaluation.add_argument("--dry-run", action="store_true", help="list the commands, run nothing")
    tsne = sub.add_parser(
        "tsne", help="record the states and t-SNE of the file's tsne entries (figure 9) that the runs allow"
    )
    tsne.add_argument("--matrix", type=Path, default=DEFAULT_MATRIX, help="the campaign file")
    tsne.add_argument("--outputs", type=Path, help="where the runs are (default: the file's)")
    tsne.add_argument("--records", type=Path, help="where the records go (default: the file's)")
    record = sub.add_parser("record", help="record mcrs-train runs or mcrs-eval results")
    record.add_argument("run_dirs", nargs="+", type=Path, metavar="RUN_DIR")
    record.add_argument(
        "--matrix",
        type=Path,
        help="a campaign file: the records go to its root (section6_paper.yaml: results/records/paper)",
    )
    record.add_argument(
        "--records", type=Path, help=f"where the records go (default: --matrix's, else {RECORDS_DIR})"
    )
    record.add_argument(
        "--prune", action="store_true", help="drop the replay and memory from a finished run's last.pt"
    )
    record.add_argument(
        "--replace", action="store_true", help="overwrite a record of another run of the same point"
    )
    report = sub.add_parser(
        "report", help="mcrs-report on the records of the selected points and the heuristics"
    )
    matrix_options(report)
    report.add_argument("--out", type=Path, required=True, help="folder for the figures and tables")
    report.add_argument("--env", default=None, help="the map (default: the selected points' only map)")
    return parser


def _points(args: argparse.Namespace) -> tuple[list[Point], int]:
    points, _ = load_matrix(args.matrix)
    points = select(points, args.only)
    return points, budget_steps(points[0].budget) if points else 0


def _where(state: Progress, records: Path) -> str:
    """The status table's last column: the record or run directory, and who trains the point now. A missing
    point's earlier run starts over here unless another runner, with its own outputs, trains it now."""
    holder = None if state.state == "done" else claim_holder(records, state.point)
    if holder is not None:
        return "; ".join(filter(None, [f"training now: {holder}", state.note]))
    if state.state == "missing" and state.note:
        return f"{state.note}, no checkpoint of it here: starts from 0"
    return state.note


def figures_line(states: list[Progress]) -> str:
    """How many of each figure's points are done, in the file's order (a point may serve several)."""
    done: dict[str, list[bool]] = {}
    for state in states:
        for figure in state.point.figures:
            done.setdefault(figure, []).append(state.state == "done")
    return "done by figure: " + ", ".join(f"{f} {sum(d)} of {len(d)}" for f, d in done.items())


def cmd_status(args: argparse.Namespace) -> int:
    _check_jobs(args.jobs)
    points, total = _points(args)
    campaign = Campaign(points, args.outputs, args.records, total, args.jobs)
    states = campaign.status()
    rows = [
        [s.point.id, ",".join(s.point.figures), s.state, f"{s.env_steps:,}", _where(s, args.records)]
        for s in states
    ]
    print(markdown(["point", "figures", "state", "env steps", "where"], rows))
    counts = Counter(s.state for s in states)
    print(
        f"\n{len(states)} points ({total:,} env steps each): " + ", ".join(f"{counts[k]} {k}" for k in STATES)
    )
    print(figures_line(states))
    print(left_line(campaign.left_s(states), args.jobs))
    for line in summary(_evaluations(args), points, args.records):
        print(line)
    for line in figure9.summary(_tsne(args), args.records):
        print(line)
    return 0


def _check_jobs(jobs: int, threads: int = 1) -> None:
    cores = os.cpu_count() or 1
    if not 1 <= jobs <= cores:  # each run has one torch thread: more runs than cores only queue
        raise SystemExit(f"mcrs-campaign: error: --jobs={jobs}: must be >= 1 and <= {cores} (CPU cores)")
    if not 1 <= threads <= cores // jobs:  # threads of one run that wait for a core spin (OpenMP)
        raise SystemExit(
            f"mcrs-campaign: error: --threads={threads}: must be >= 1, with --jobs x --threads <= {cores} "
            f"(CPU cores; --jobs={jobs})"
        )


def cmd_run(args: argparse.Namespace) -> int:
    _check_jobs(args.jobs, args.threads)
    if not (math.isfinite(args.hours) and 0 < args.hours <= MAX_HOURS):
        raise SystemExit(
            f"mcrs-campaign: error: --hours={args.hours}: must be > 0 and <= {MAX_HOURS} (a year)"
        )
    for flag, given in (("--finish-first", args.finish_first), ("--finish-only", args.finish_only)):
        if given and not args.fill:
            raise SystemExit(
                f"mcrs-campaign: error: {flag} needs --fill (without it no run starts that cannot end in time)"
            )
    points, total = _points(args)
    evaluations = [] if args.no_evaluate else _evaluations(args)
    campaign = Campaign(
        points,
        args.outputs,
        args.records,
        total,
        args.jobs,
        not args.keep_replay,
        evaluations,
        args.threads,
        _tsne(args),
        make_tsne=not args.no_evaluate,
    )
    if args.dry_run:
        print("\n".join(campaign.dry_run(args.hours, args.fill, args.finish_first, args.finish_only)))
        return 0
    return campaign.run(args.hours, args.fill, args.finish_first, args.finish_only)


def _evaluations(args: argparse.Namespace) -> list[Evaluation]:
    """The campaign file's evaluations, only those named by ``--evaluation`` if given."""
    _, titles = load_matrix(args.matrix)
    evaluations = load_evaluations(args.matrix, set(titles))
    names = [e.name for e in evaluations]
    chosen = getattr(args, "evaluation", [])
    unknown = [n for n in chosen if n not in names]
    if unknown:
        raise MatrixError(
            f"--evaluation={','.join(unknown)}: allowed values are {', '.join(names) or 'none'}"
        )
    return [e for e in evaluations if not chosen or e.name in chosen]


def _tsne(args: argparse.Namespace) -> list[figure9.TsneEntry]:
    """The campaign file's tsne entries, resolved against all of its points."""
    return figure9.load_tsne(args.matrix, load_matrix(args.matrix)[0])


def cmd_tsne(args: argparse.Namespace) -> int:
    """Every t-SNE record the finished runs allow; 0, or 1 if one failed."""
    lines = figure9.pending(_tsne(args), args.outputs, args.records)
    for line in lines:
        print(line, flush=True)
    return 1 if any(line.startswith("failed: ") for line in lines) else 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    points, _ = _points(args)
    return evaluate(_evaluations(args), points, args.outputs, args.records, args.dry_run)


def cmd_record(args: argparse.Namespace) -> int:
    failed = 0
    for run_dir in args.run_dirs:
        try:
            path, record = make_record(run_dir, args.records)
            outcome = write_record(path, record, replace=args.replace)
        except (RecordError, ckpt.CheckpointError) as error:
            print(f"mcrs-campaign: error: {error}", file=sys.stderr)
            failed += 1
            continue
        except OSError as error:
            # --records a file, an unwritable folder, a full disk: the record is whole or absent
            print(
                f"mcrs-campaign: error: cannot write the record of {run_dir}: {describe_os_error(error)}",
                file=sys.stderr,
            )
            failed += 1
            continue
        steps = record.get("checkpoint_env_steps")
        what = (
            f"{record['status']} at {steps:,} env steps" if record["kind"] == "training" else record["kind"]
        )
        print(f"{outcome} {path} ({what})")
        if args.prune:
            if record["kind"] != "training" or record["status"] != "finished":
                print(
                    f"  not pruned: {run_dir} is not a finished training run (a stopped run stays resumable)"
                )
            else:
                before, after = ckpt.prune_bulk(run_dir)
                print(
                    f"  pruned {ckpt.checkpoint_path(run_dir)}: {before / 1e6:.0f} MB -> {after / 1e6:.0f} MB"
                )
    return 1 if failed else 0


def heuristic_folders(evaluations: list[Evaluation], records: Path, env: str) -> list[Path]:
    """The records of the file's heuristics-only evaluations on ``env`` (the learners' own evaluation
    episodes: what the claims hold a learner against), else the older ``<records>/heuristics/<env>``."""
    folders = [
        records / e.name / variant / "eval" / env
        for e in evaluations
        if not e.trained
        for variant, _ in e.variants
    ]
    found = [f for f in folders if f.is_dir()]
    older = records / "heuristics" / env
    return found or ([older] if older.is_dir() else [])


def cmd_report(args: argparse.Namespace) -> int:
    from mcrs_lab.analysis.report import main as report_main

    points, _ = _points(args)
    paths = [p.record_path(args.records) for p in points if p.record_path(args.records).is_file()]
    maps = sorted({p.env for p in points})
    env = args.env or (maps[0] if len(maps) == 1 else None)
    if env is None:
        raise SystemExit(
            f"mcrs-campaign: error: the points are on {', '.join(maps)}: pass --env (one of them)"
        )
    if not paths:
        raise SystemExit("mcrs-campaign: error: no record of the selected points yet (mcrs-campaign status)")
    print(f"{len(paths)} of {len(points)} points recorded", flush=True)
    return report_main(
        [
            *map(str, paths),
            *map(str, heuristic_folders(_evaluations(args), args.records, env)),
            "--env",
            env,
            "--out",
            str(args.out),
        ]
    )


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        commands = {
            "status": cmd_status,
            "run": cmd_run,
            "evaluate": cmd_evaluate,
            "tsne": cmd_tsne,
            "record": cmd_record,
            "report": cmd_report,
        }
        if getattr(args, "matrix", None) is not None:
            records, outputs = campaign_roots(args.matrix)
            args.records = args.records or records
            args.outputs = getattr(args, "outputs", None) or outputs
        args.records = args.records or RECORDS_DIR  # mcrs-campaign record without --matrix
        return commands[args.command](args)
    except (MatrixError, CampaignBusy, RecordError, figure9.tsne.TsneRecordError) as error:
        raise SystemExit(f"mcrs-campaign: error: {error}") from None


if __name__ == "__main__":
    sys.exit(main())
