"""The campaign's points (mcrs_lab/campaign/section6_paper.yaml): which mcrs-train runs make which figure.

A point is one run: an experiment preset, a map, an algorithm, its swept values and a seed, at the
campaign's budget. Its run directory and its record path follow from it, so whether it is done can be
read from the disk alone (mcrs_lab.campaign.progress).
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from mcrs.experiment.commands.cli import file_override_problem
from mcrs.experiment.schema import CONFIG_DIR
from mcrs.experiment.util.untrusted import UntrustedInput, finite_number, plain_name, read_yaml
from mcrs_lab.analysis.records import RECORDS_DIR, point_name, swept_fields

#: The section-6 campaign on the paper's task: beside this module, not in conf/, where Hydra would offer
#: it to mcrs-train as a config group.
DEFAULT_MATRIX = Path(__file__).resolve().parent / "section6_paper.yaml"
#: Where a campaign file without a ``name`` keeps its runs.
OUTPUTS_DIR = Path("outputs/campaign")
FIGURE_KEYS = {"title", "experiment", "env", "algo", "sweep", "also", "seeds"}
FILE_KEYS = {"name", "budget", "seeds", "figures", "overrides", "evaluations", "tsne"}


class MatrixError(ValueError):
    """A campaign file or an ``--only`` filter that cannot be used."""


#: Seeds are mcrs-train's: in [0, 2**63 - 1].
MAX_SEED = 2**63 - 1


def plain(value: Any, what: str) -> str:
    """``value`` as a plain name (it becomes a folder of the outputs or the records), else MatrixError."""
    try:
        return plain_name(value, what)
    except UntrustedInput as error:
        raise MatrixError(str(error)) from None


def load_campaign_file(path: Path) -> dict[str, Any]:
    """The campaign file as plain data, bounded before parsing (no aliases, size and depth limits)."""
    try:
        spec = read_yaml(path)
    except UntrustedInput as error:
        raise MatrixError(str(error)) from None
    if not isinstance(spec, dict) or "figures" not in spec:
        raise MatrixError(
            f"{path}: not a campaign file: a mapping with figures (and name, budget, seeds, overrides, "
            "evaluations, tsne)"
        )
    unknown = sorted(str(k) for k in set(spec) - FILE_KEYS)
    if unknown:
        raise MatrixError(f"{path}: unknown keys {unknown}; allowed: {sorted(FILE_KEYS)}")
    return spec


def _option(group: str, value: Any, where: str) -> str:
    """``value`` as an option of the config group ``group`` (conf/<group>/<value>.yaml)."""
    name = plain(value, f"{where}: {group}")
    allowed = sorted(p.stem for p in Path(CONFIG_DIR, group).glob("*.yaml"))
    if name not in allowed:
        raise MatrixError(f"{where}: {group}={name!r}: allowed values are {', '.join(allowed)}")
    return name


def campaign_roots(path: Path) -> tuple[Path, Path]:
    """The records and outputs folders of a campaign file: ``results/records/<name>`` and ``outputs/<name>``
    for a file with a ``name``, ``results/records`` and ``outputs/campaign`` for one without.

    The name is a plain name, never a path, so a file cannot send its runs outside these roots."""
    _check_file(path)
    name = load_campaign_file(path).get("name")
    if name is None:
        return RECORDS_DIR, OUTPUTS_DIR
    name = plain(name, f"{path}: name")
    return RECORDS_DIR / name, Path("outputs") / name


def _check_file(path: Path) -> None:
    if path.is_dir():
        raise MatrixError(f"--matrix={path}: a folder: name the campaign file (a .yaml) in it")
    if not path.is_file():
        raise MatrixError(f"--matrix={path}: no such file")


#: A config group's option as a campaign file names it (an evaluation's ``algo`` too).
figure_option = _option


def _seed(value: Any, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_SEED:
        raise MatrixError(f"{where}: seeds: {value!r} is not a whole number in [0, 2**63 - 1]")
    return value


@dataclass(frozen=True)
class Point:
    """One mcrs-train run of the campaign."""

    experiment: str
    env: str
    algo: str
    seed: int
    budget: str
    settings: tuple[tuple[str, Any], ...] = ()  # the swept values: (("algo.memory.delta", 0.13),)
    overrides: tuple[str, ...] = ()  # fixed per-algorithm overrides (not part of the name)
    figures: tuple[str, ...] = field(default=(), compare=False)

    @property
    def name(self) -> str:
        return point_name(self.env, self.algo, self.seed, dict(self.settings))

    @property
    def id(self) -> str:
        return f"{self.experiment}/{self.name}"

    def run_dir(self, outputs: Path) -> Path:
        return outputs / self.experiment / self.budget / self.name

    def record_path(self, records: Path) -> Path:
        return records / self.experiment / self.budget / f"{self.name}.json"

    def tags(self) -> set[str]:
        """What ``--only`` can name: a figure, an experiment, a map, an algorithm, ``seed<k>``, the id."""
        return {*self.figures, self.experiment, self.env, self.algo, f"seed{self.seed}", self.id}

    def train_command(self, outputs: Path, threads: int = 1) -> list[str]:
        """``mcrs-train`` for a fresh run: the preset with every swept field fixed, one run, ``threads``
        torch threads (one: two runs side by side use two cores best, docs/PERFORMANCE.md)."""
        values = [f"{k}={v}" for k, v in self.settings]
        return [
            sys.executable,
            "-m",
            "mcrs.train",
            f"experiment={self.experiment}",
            f"budget={self.budget}",
            f"env={self.env}",
            f"algo={self.algo}",
            *values,
            *self.overrides,
            f"seed={self.seed}",
            f"threads={threads}",
            "hydra.mode=RUN",
            f"hydra.run.dir={self.run_dir(outputs)}",
        ]

    def resume_command(self, outputs: Path, total_env_steps: int, threads: int = 1) -> list[str]:
        """``mcrs-train resume=`` to the budget's length; Hydra's own files of the first launch are kept."""
        run_dir = self.run_dir(outputs)
        return [
            sys.executable,
            "-m",
            "mcrs.train",
            f"resume={run_dir}",
            f"train.total_env_steps={total_env_steps}",
            f"threads={threads}",
            # a run first launched before checkpoint_minutes' default of 10 keeps its saved 0 otherwise
            "train.checkpoint_minutes=10",
            "logger.progress_bar=false",
            f"hydra.run.dir={run_dir}",
            "hydra.output_subdir=null",
        ]


def budget_steps(budget: str) -> int:
    """``train.total_env_steps`` of ``conf/budget/<budget>.yaml``: the length every point must reach."""
    path = Path(CONFIG_DIR, "budget", f"{budget}.yaml")
    if not path.is_file():
        allowed = sorted(p.stem for p in path.parent.glob("*.yaml"))
        raise MatrixError(f"budget={budget!r}: allowed values are {', '.join(allowed)}")
    return int(OmegaConf.load(path).train.total_env_steps)


#: The key of ``overrides`` whose overrides every point gets (before its algorithm's own).
ALL_POINTS = "all"


def _as_list(value: Any) -> list[Any]:
    return list(value) if isinstance(value, (list, tuple)) else [value]


#: What ``Point.train_command`` sets for each point: a campaign file's overrides may not.
TRAIN_KEYS = ("experiment", "budget", "env", "algo", "seed", "threads")


def check_overrides(overrides: Any, where: str, reserved: tuple[str, ...]) -> tuple[str, ...]:
    """``overrides`` (a list of ``key=value``) as a tuple, each one a config value the tool may pass on:
    no Hydra setting, no ``resume``/``overwrite``, none of ``reserved``, no path (``file_override_problem``
    in mcrs.experiment.commands.cli), else MatrixError naming ``where`` and the override."""
    out = []
    for override in _as_list(overrides):
        problem = file_override_problem(override, reserved)
        if problem:
            raise MatrixError(f"{where}: {problem}")
        out.append(str(override))
    return tuple(out)


def _overrides(spec: Any, path: Path) -> dict[str, tuple[str, ...]]:
    """The campaign file's ``overrides:`` (``all`` and per algorithm), each checked."""
    if not isinstance(spec, dict):
        raise MatrixError(f"{path}: overrides: a mapping of 'all' or an algorithm to lists of overrides")
    return {str(k): check_overrides(v, f"{path}: overrides {k}", TRAIN_KEYS) for k, v in spec.items()}


def load_matrix(path: Path = DEFAULT_MATRIX) -> tuple[list[Point], dict[str, str]]:
    """Every point of the campaign file (each once, in the file's order, seed by seed within a
    figure), and each figure's title."""
    _check_file(path)
    spec = load_campaign_file(path)
    budget = plain(spec.get("budget", "campaign"), f"{path}: budget")
    seeds = [_seed(s, str(path)) for s in _as_list(spec.get("seeds", [0]))]
    budget_steps(budget)  # an unknown budget fails here, naming the allowed ones
    overrides = _overrides(spec.get("overrides") or {}, path)
    figures = spec.get("figures") or {}
    if not isinstance(figures, dict):
        raise MatrixError(f"{path}: figures: a mapping of figure names to entries")
    points: dict[Point, list[str]] = {}
    titles = {}
    for name, fig in figures.items():
        where = f"{path}: figure {name}"
        if not isinstance(fig, dict) or not {"experiment", "env", "algo"} <= set(fig):
            raise MatrixError(
                f"{where}: a mapping with experiment, env and algo (and title, sweep, also, seeds)"
            )
        unknown = set(fig) - FIGURE_KEYS
        if unknown:
            raise MatrixError(
                f"{path}: figure {name}: unknown keys {sorted(unknown)}; allowed: {sorted(FIGURE_KEYS)}"
            )
        titles[name] = str(fig.get("title", name))
        experiment = _option("experiment", fig["experiment"], where)
        envs = [_option("env", e, where) for e in _as_list(fig["env"])]
        algos = [_option("algo", a, where) for a in _as_list(fig["algo"])]
        sweep = fig.get("sweep") or {}
        if not isinstance(sweep, dict):
            raise MatrixError(f"{where}: sweep: a mapping of fields to lists of values")
        for key, values in sweep.items():
            if not all(finite_number(v) or v == math.inf for v in _as_list(values)):
                raise MatrixError(f"{where}: sweep {key}={values!r}: numbers only (not NaN)")
        bad = [k for k in sweep if k not in swept_fields(experiment)]
        if bad:
            raise MatrixError(
                f"{path}: figure {name}: sweep {bad} is not swept by experiment={experiment} "
                f"(it sweeps {list(swept_fields(experiment)) or 'nothing besides map, algo and seed'})"
            )
        combos: list[tuple[tuple[str, Any], ...]] = [()]
        for key, values in sweep.items():
            combos = [(*c, (key, v)) for c in combos for v in _as_list(values)]
        # A figure's own `seeds` replace the file's: a probe at one seed beside a result at three.
        figure_seeds = [_seed(s, where) for s in _as_list(fig["seeds"])] if "seeds" in fig else seeds
        for seed in figure_seeds:
            for env in envs:
                for algo in algos:
                    for combo in combos:
                        fixed = (*overrides.get(ALL_POINTS, ()), *overrides.get(algo, ()))
                        point = Point(experiment, env, algo, seed, budget, combo, fixed)
                        points.setdefault(point, []).append(name)
    for name, fig in figures.items():  # a figure's `also`: points of another figure that serve it too
        for other, algos in (fig.get("also") or {}).items():
            if other not in figures:
                raise MatrixError(f"{path}: figure {name}: also names {other!r}; figures are {list(figures)}")
            for point, names in points.items():
                if other in names and point.algo in _as_list(algos) and name not in names:
                    names.append(name)
    out = [
        Point(p.experiment, p.env, p.algo, p.seed, p.budget, p.settings, p.overrides, tuple(names))
        for p, names in points.items()
    ]
    return out, titles


def select(points: list[Point], only: list[str]) -> list[Point]:
    """The points matching every ``--only`` value; within one value, comma-separated names are
    alternatives (``--only fig7 --only qmix,vdn``: figure 7's QMIX and VDN runs). A figure's name means
    the figure, where an experiment has the same name (figure ``shields_gamma`` is two of experiment
    ``shields_gamma``'s points)."""
    known = set().union(*(p.tags() for p in points)) if points else set()
    figures = {f for p in points for f in p.figures}
    for value in only:
        names = [n for n in value.split(",") if n]
        unknown = [n for n in names if n not in known]
        if unknown or not names:
            kinds = sorted(n for n in known if "/" not in n)
            raise MatrixError(
                f"--only={value}: unknown {', '.join(unknown) or 'empty value'}; allowed: {', '.join(kinds)} "
                "or a point id (mcrs-campaign status lists them)"
            )
        points = [p for p in points if any(_matches(p, n, figures) for n in names)]
    return points


def _matches(point: Point, name: str, figures: set[str]) -> bool:
    return name in point.figures if name in figures else name in point.tags()
