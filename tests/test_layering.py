"""The package's layers (docs/ARCHITECTURE.md): no package imports one above it, no import cycles between
packages nor between the modules of one package, no module over 500 lines, and ``import mcrs.env`` loads
neither PettingZoo nor anything above. The library and the lab apart: ``mcrs`` never imports the lab
(``mcrs_lab``: campaign, analysis) nor the benchmarks (``mcrs_benchmarks``, the root folder benchmarks/);
they import ``mcrs``, and the same rules hold inside them (layers, cycles, 500 lines).

Inside ``mcrs/experiment/`` the same holds for its rooms (``EXPERIMENT_ROOMS``): the loop (``training``) never
imports the command line (``commands``), and the config's checks (``schema``, ``config``) import neither the
loop nor the run on disk.

The imports are read from the source (``ast``), every ``import`` statement counted: at module level,
inside functions (lazy imports) and under ``if TYPE_CHECKING``. A "package" is a sub-package of
``mcrs`` (``mcrs/env/``) or a top-level module (``mcrs/train.py``); ``mcrs/__init__.py`` is ``mcrs``.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from collections.abc import Iterable
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
ROOT = REPO / "mcrs"
LAB = REPO / "mcrs_lab"
BENCHMARKS = REPO / "benchmarks"  # installed as mcrs_benchmarks (pyproject.toml's package-dir)
#: Each import package of the distribution and its folder.
TREES = {"mcrs": ROOT, "mcrs_lab": LAB, "mcrs_benchmarks": BENCHMARKS}
MAX_LINES = 500

#: Bottom to top. A package may import packages of its own layer or below, never above; within a layer
#: the imports must not form a cycle. A new package must be placed here before the test passes.
LAYERS: tuple[tuple[str, ...], ...] = (
    ("choices",),  # the config's choice lists (mcrs/choices.py): the standard library only
    ("env",),  # the simulator, its adapters and layouts: imports nothing else of mcrs
    ("models", "memory"),  # networks; the episodic buffer (both read env's layouts)
    ("objectives",),  # the losses over the models
    ("experiment", "policies"),  # training, checkpoints; policies (heuristics, trained checkpoints)
    (  # applications: pictures and tables, other tasks, the command lines, the package root
        "viz",
        "tasks",
        "evaluate",
        "render_episode",
        "export_agent",
        "train",
        "mcrs",
    ),
)
LAYER = {package: level for level, packages in enumerate(LAYERS) for package in packages}
#: The lab's packages, bottom to top (the campaign records its runs with the analysis' records).
LAB_LAYERS: tuple[tuple[str, ...], ...] = (("analysis",), ("campaign",), ("mcrs_lab",))
LAB_LAYER = {package: level for level, packages in enumerate(LAB_LAYERS) for package in packages}

#: The rooms of mcrs/experiment/ (mcrs/experiment/__init__.py) and the rooms each may import besides itself.
#: ``config`` is the two modules schema.py and config.py; the package's __init__ is ``experiment``.
EXPERIMENT_ROOMS: dict[str, frozenset[str]] = {
    "util": frozenset(),  # small helpers: atomic writes, untrusted text, tables, threads, messages
    "config": frozenset({"util"}),  # the typed config and the checks of its values: never the loop
    "run": frozenset({"util", "config"}),  # the run on disk: directory, checkpoints, logs, saved state
    "training": frozenset({"util", "config", "run"}),  # the loop: never the command line
    "commands": frozenset({"util", "config", "run"}),  # the command lines' Hydra glue: never the loop
    "experiment": frozenset(),  # the package's __init__ (a docstring)
}
EXPERIMENT = "mcrs.experiment"


#: Known imports against the layers, each with the change that removes it (none: the list only shrinks).
ALLOWED_UPWARD: dict[tuple[str, str], str] = {}

#: Known imports that close a cycle between the modules of one package, ``(file, imported module)``, each
#: with the change that removes it (none: the list only shrinks).
ALLOWED_MODULE_CYCLES: dict[tuple[str, str], str] = {}

#: Modules allowed over 500 lines (none: the list only shrinks).
ALLOWED_LONG: dict[str, str] = {}


def package_of(module: str) -> str:
    """``mcrs.env.core`` -> ``env``; ``mcrs.train`` -> ``train``; ``mcrs`` -> ``mcrs`` (and
    ``mcrs_lab.analysis.runs`` -> ``analysis``)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def _top(root: Path) -> str:
    """The import name of the tree ``root``: its folder's name, but ``mcrs_benchmarks`` for benchmarks/."""
    return next((name for name, folder in TREES.items() if folder == root), root.name)


def module_name(path: Path, root: Path = ROOT) -> str:
    relative = path.relative_to(root).with_suffix("")
    parts = relative.parts[:-1] if relative.name == "__init__" else relative.parts
    return ".".join([_top(root), *parts])


def all_imports(path: Path, root: Path = ROOT) -> set[str]:
    """Every module that ``path`` imports (absolute or relative, anywhere in the file), of any package."""
    return _imports(path, root, top=None)


def imported_modules(path: Path, root: Path = ROOT) -> set[str]:
    """Every module of ``root``'s own package that ``path`` imports (``mcrs`` for mcrs/)."""
    return _imports(path, root, top=_top(root))


def _imports(path: Path, root: Path, top: str | None) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    here = module_name(path, root).split(".")
    is_package = path.name == "__init__.py"
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against this module's package
                base = here if is_package else here[:-1]
                base = base[: len(base) - (node.level - 1)]
                target = ".".join([*base, node.module] if node.module else base)
            else:
                target = node.module or ""
            for alias in node.names:  # ``from mcrs.experiment.run import checkpoint`` imports that module
                submodule = f"{target}.{alias.name}"
                found.add(submodule if target == _top(root) or _is_module(submodule, root) else target)
    return {m for m in found if top is None or m == top or m.startswith(top + ".")}


def _is_module(module: str, root: Path) -> bool:
    """Whether ``mcrs.a.b`` is a file (``mcrs/a/b.py``) or a package (``mcrs/a/b/``) under ``root``."""
    first, *rest = module.split(".")
    if first != _top(root):
        return False
    path = root.joinpath(*rest)
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def import_edges(root: Path = ROOT) -> list[tuple[str, str, str]]:
    """``(file relative to mcrs/, importing package, imported package)`` for every cross-package import."""
    edges = []
    for path in sorted(root.rglob("*.py")):
        source = package_of(module_name(path, root))
        for module in sorted(imported_modules(path, root)):
            target = package_of(module)
            if target != source:
                edges.append((path.relative_to(root).as_posix(), source, target))
    return edges


def upward(edges: Iterable[tuple[str, str, str]], layer: dict[str, int] = LAYER) -> list[str]:
    """The imports of a package above the importer's layer (allowed ones aside), one line each."""
    return [
        f"{file}: {source} (layer {layer[source]}) imports {target} (layer {layer[target]})"
        for file, source, target in edges
        if layer[target] > layer[source] and (file, target) not in ALLOWED_UPWARD
    ]


def module_edges(root: Path = ROOT) -> list[tuple[str, str, str]]:
    """``(file relative to mcrs/, importing module, imported module)`` for every import between two modules
    of one package (``mcrs.experiment.training.trainer`` -> ``mcrs.experiment.config``); the benchmarks' modules
    are one package."""
    flat = _top(root) == "mcrs_benchmarks"
    edges = []
    for path in sorted(root.rglob("*.py")):
        source = module_name(path, root)
        for module in sorted(imported_modules(path, root)):
            same = flat or package_of(module) == package_of(source)
            if module != source and same and _is_module(module, root):
                edges.append((path.relative_to(root).as_posix(), source, module))
    return edges


def module_cycles(edges: Iterable[tuple[str, str, str]]) -> list[str]:
    """Each cycle between the modules of a package (allowed imports aside), as one line naming its
    modules and the imports that close it, so that the message says which import to cut."""
    kept = [
        (file, source, target)
        for file, source, target in edges
        if (file, target) not in ALLOWED_MODULE_CYCLES
    ]
    lines = []
    for component in cycles(kept, allowed={}):
        inside = [
            f"{file} imports {target}" for file, source, target in kept if {source, target} <= set(component)
        ]
        lines.append(f"{' <-> '.join(component)}: {'; '.join(inside)}")
    return lines


def cycles(
    edges: Iterable[tuple[str, str, str]], allowed: dict[tuple[str, str], str] = ALLOWED_UPWARD
) -> list[list[str]]:
    """The cycles of the graph ``importer -> imported`` (strongly connected components of more than one
    node; Tarjan); the edges ``(file, imported)`` in ``allowed`` left out."""
    graph: dict[str, set[str]] = {}
    for file, source, target in edges:
        if (file, target) not in allowed:
            graph.setdefault(source, set()).add(target)
            graph.setdefault(target, set())
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for succ in sorted(graph[node]):
            if succ not in index:
                visit(succ)
                low[node] = min(low[node], low[succ])
            elif succ in stack:
                low[node] = min(low[node], index[succ])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def room_of(module: str) -> str | None:
    """``mcrs.experiment.training.trainer`` -> ``training``; ``mcrs.experiment.config`` -> ``config``;
    None outside mcrs/experiment/."""
    parts = module.split(".")
    if parts[:2] != EXPERIMENT.split("."):
        return None
    if len(parts) == 2:
        return "experiment"
    return "config" if parts[2] in ("schema", "config") else parts[2]


def room_breaches(edges: Iterable[tuple[str, str, str]]) -> list[str]:
    """The imports between the rooms of mcrs/experiment/ that ``EXPERIMENT_ROOMS`` does not allow, one line
    each (``edges`` as :func:`module_edges` gives them)."""
    found = []
    for file, source, target in edges:
        here, there = room_of(source), room_of(target)
        if here is None or there is None or here == there:
            continue
        if there not in EXPERIMENT_ROOMS.get(here, frozenset()):
            found.append(f"{file}: the {here} room imports the {there} room ({target})")
    return found


# ------------------------------------------------------------------------------------------------ tests
def test_every_package_has_a_layer() -> None:
    packages = {package_of(module_name(path)) for path in ROOT.rglob("*.py")}
    missing = sorted(packages - set(LAYER))
    assert not missing, f"packages without a layer (add them to LAYERS and docs/ARCHITECTURE.md): {missing}"


def test_no_package_imports_one_above_it() -> None:
    problems = upward(import_edges())
    assert not problems, "imports against the layers:\n" + "\n".join(problems)


def test_no_import_cycles_between_packages() -> None:
    assert cycles(import_edges()) == []


def test_no_import_cycles_between_the_modules_of_a_package() -> None:
    """Lazy imports count: a cycle hidden in a function still ties the modules together (one cannot be
    understood, tested or moved without the other)."""
    found = module_cycles(module_edges())
    assert not found, "import cycles inside a package:\n" + "\n".join(found)


def test_the_library_imports_neither_the_lab_nor_the_benchmarks() -> None:
    """``mcrs`` is what a user imports: nothing of it may need the research tools (lazy imports count)."""
    found = [
        f"{path.relative_to(REPO).as_posix()} imports {module}"
        for path in sorted(ROOT.rglob("*.py"))
        for module in sorted(all_imports(path, ROOT))
        if module.split(".")[0] in ("mcrs_lab", "mcrs_benchmarks", "benchmarks")
    ]
    assert not found, "the library imports the lab:\n" + "\n".join(found)


def test_the_lab_and_the_benchmarks_import_only_the_library_and_the_lab() -> None:
    """The lab imports mcrs, never the benchmarks; the benchmarks import mcrs, never the lab."""
    found = [
        f"{path.relative_to(REPO).as_posix()} imports {module}"
        for root, other in (
            (LAB, ("mcrs_benchmarks", "benchmarks")),
            (BENCHMARKS, ("mcrs_lab", "benchmarks")),
        )
        for path in sorted(root.rglob("*.py"))
        for module in sorted(all_imports(path, root))
        if module.split(".")[0] in other
    ]
    assert not found, "\n".join(found)


def test_the_lab_keeps_its_layers_and_has_no_cycles() -> None:
    """Inside mcrs_lab: the analysis never imports the campaign; no cycle between the modules of the
    analysis, the campaign or the benchmarks."""
    packages = {package_of(module_name(path, LAB)) for path in LAB.rglob("*.py")}
    assert packages <= set(LAB_LAYER), f"lab packages without a layer (add them to LAB_LAYERS): {packages}"
    edges = import_edges(LAB)
    assert upward(edges, LAB_LAYER) == [] and cycles(edges) == []
    found = module_cycles(module_edges(LAB)) + module_cycles(module_edges(BENCHMARKS))
    assert not found, "import cycles inside the lab:\n" + "\n".join(found)


def test_the_distribution_ships_every_package() -> None:
    """pyproject.toml lists the packages (the benchmarks' folder is mapped to mcrs_benchmarks): a package
    folder missing from the list would be left out of wheels, and its command would fail after
    ``pip install .``."""
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    settings = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    on_disk = {module_name(init, root) for root in TREES.values() for init in root.rglob("__init__.py")}
    assert set(settings["packages"]) == on_disk
    assert settings["package-dir"] == {"mcrs_benchmarks": "benchmarks"}


def test_allow_lists_are_current() -> None:
    """An allowed exception that is gone must leave the list, so that it cannot come back unnoticed."""
    edges = {(file, target) for file, _, target in import_edges()}
    stale = [edge for edge in ALLOWED_UPWARD if edge not in edges]
    inner = {(file, target) for file, _, target in module_edges()}
    stale += [edge for edge in ALLOWED_MODULE_CYCLES if edge not in inner]
    stale += [f for f in ALLOWED_LONG if not (ROOT / f).is_file() or _lines(ROOT / f) <= MAX_LINES]
    assert not stale, f"allow-list entries no longer needed (remove them): {stale}"


def _lines(path: Path) -> int:
    return len(path.read_text().splitlines())


def test_no_module_over_500_lines() -> None:
    """In the library, the lab and the benchmarks."""
    long = {
        path.relative_to(REPO).as_posix(): _lines(path)
        for root in TREES.values()
        for path in sorted(root.rglob("*.py"))
        if _lines(path) > MAX_LINES
    }
    offenders = {f: n for f, n in long.items() if f not in ALLOWED_LONG}
    assert not offenders, f"modules over {MAX_LINES} lines: {offenders}"


def test_the_checks_catch_an_upward_import_and_a_cycle(tmp_path: Path) -> None:
    """The checker itself, on a small tree: a lazy ``import mcrs.policies`` in env/core.py is an upward
    import, and a relative import of models from env (models imports env) is both upward and a cycle."""
    tree = tmp_path / "mcrs"
    for name in ("env", "models"):
        (tree / name).mkdir(parents=True)
        (tree / name / "__init__.py").write_text("")
    (tree / "__init__.py").write_text("")
    (tree / "env" / "core.py").write_text(
        "def f():\n    import mcrs.policies\n    from ..models import agent\n"
    )
    (tree / "models" / "agent.py").write_text("from mcrs.env.layout import MapImage\n")
    edges = import_edges(tree)
    assert ("env/core.py", "env", "policies") in edges and ("env/core.py", "env", "models") in edges
    assert any("env (layer 1) imports policies (layer 4)" in line for line in upward(edges))
    assert cycles(edges) == [["env", "models"]]


def test_the_check_catches_a_module_cycle_through_a_lazy_or_relative_import(tmp_path: Path) -> None:
    """In one package: ``a`` imports ``b`` lazily, ``b`` imports ``a`` by ``from . import a``; ``c`` imports
    ``b`` only (no cycle), and ``from mcrs.pkg import c`` names the module, not the package."""
    package = tmp_path / "mcrs" / "pkg"
    package.mkdir(parents=True)
    (tmp_path / "mcrs" / "__init__.py").write_text("")
    (package / "__init__.py").write_text("")
    (package / "a.py").write_text("def f():\n    from mcrs.pkg.b import g\n")
    (package / "b.py").write_text("from . import a\n")
    (package / "c.py").write_text("from mcrs.pkg import b\n")
    (package / "d.py").write_text("from mcrs.pkg import c\n")
    edges = module_edges(tmp_path / "mcrs")
    assert ("pkg/d.py", "mcrs.pkg.d", "mcrs.pkg.c") in edges and (
        "pkg/d.py",
        "mcrs.pkg.d",
        "mcrs.pkg",
    ) not in edges
    assert module_cycles(edges) == [
        "mcrs.pkg.a <-> mcrs.pkg.b: pkg/a.py imports mcrs.pkg.b; pkg/b.py imports mcrs.pkg.a"
    ]


def test_importing_the_low_layers_loads_neither_pettingzoo_nor_anything_above() -> None:
    """In a fresh interpreter: ``import mcrs.env`` loads only mcrs.env (no PettingZoo: the adapter is a
    lazy attribute), then mcrs.models and mcrs.memory load nothing above their layer."""
    code = """
import json, sys
loaded = {}
def snapshot(name):
    loaded[name] = sorted(m for m in sys.modules if m.startswith(("mcrs", "pettingzoo")))
import mcrs.env; snapshot("env")
import mcrs.models; snapshot("models")
import mcrs.memory; snapshot("memory")
from mcrs.env import MCRSParallelEnv; snapshot("adapter")
print(json.dumps(loaded))
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    loaded = json.loads(done.stdout)
    assert [m for m in loaded["env"] if not m.startswith("mcrs.env") and m != "mcrs"] == []  # no pettingzoo
    for package in ("models", "memory"):
        above = [
            m for m in loaded[package] if m.startswith("mcrs.") and LAYER[package_of(m)] > LAYER[package]
        ]
        assert above == [] and "pettingzoo" not in loaded[package], package
    assert "pettingzoo" in loaded["adapter"] and "mcrs.env.pettingzoo_env" in loaded["adapter"]


def test_every_module_of_experiment_is_in_a_room() -> None:
    """A new folder or top-level module in mcrs/experiment/ is placed in ``EXPERIMENT_ROOMS`` first."""
    rooms = {room_of(module_name(path)) for path in (ROOT / "experiment").rglob("*.py")}
    assert rooms <= set(EXPERIMENT_ROOMS), (
        f"modules outside the rooms: {sorted(rooms - set(EXPERIMENT_ROOMS))}"
    )


def test_the_rooms_of_experiment_keep_their_order() -> None:
    """The loop never imports the command line; checking a config never imports the loop (nor the run on
    disk); lazy imports count."""
    problems = room_breaches(module_edges())
    assert not problems, "imports between the rooms of mcrs/experiment/:\n" + "\n".join(problems)


def test_the_room_check_catches_the_loop_importing_the_command_line(tmp_path: Path) -> None:
    """The checker on a small tree: callbacks importing the command line lazily, and config importing the
    loop, are breaches; the loop importing the run on disk is not."""
    experiment = tmp_path / "mcrs" / "experiment"
    for room in ("training", "commands", "run"):
        (experiment / room).mkdir(parents=True)
        (experiment / room / "__init__.py").write_text("")
    (tmp_path / "mcrs" / "__init__.py").write_text("")
    (experiment / "__init__.py").write_text("")
    (experiment / "commands" / "cli.py").write_text("")
    (experiment / "run" / "checkpoint.py").write_text("")
    (experiment / "training" / "callbacks.py").write_text(
        "from mcrs.experiment.run import checkpoint\ndef f():\n    from mcrs.experiment.commands.cli import x\n"
    )
    (experiment / "config.py").write_text("from .training import callbacks\n")
    assert room_breaches(module_edges(tmp_path / "mcrs")) == [
        "experiment/config.py: the config room imports the training room (mcrs.experiment.training.callbacks)",
        "experiment/training/callbacks.py: the training room imports the commands room "
        "(mcrs.experiment.commands.cli)",
    ]
