"""``report.md`` of ``mcrs-report``: its sections collected while the figures and tables are written, and
what was read and skipped."""

from __future__ import annotations

from pathlib import Path

from mcrs_lab.analysis.claims import Claim
from mcrs_lab.analysis.runs import Runs


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
            print(f"\nskipped {len(unique)} (each in {path}):\n{_grouped_by_reason(unique)}", flush=True)
        return path


def _grouped_by_reason(skipped: list[tuple[str, str]], listed: int = 3) -> str:
    """The terminal's list of skipped files: a reason shared by more than ``listed`` files (every run of
    another map in a campaign's records folder) is one line with their count, not one line each."""
    by_reason: dict[str, list[str]] = {}
    for path, reason in skipped:
        by_reason.setdefault(reason, []).append(path)
    lines = []
    for reason, paths in by_reason.items():
        if len(paths) > listed:
            lines.append(f"- {len(paths)} files (`{paths[0]}`, ...): {reason}")
        else:
            lines += [f"- `{p}`: {reason}" for p in paths]
    return "\n".join(lines)
