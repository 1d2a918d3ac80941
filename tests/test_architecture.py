"""The layers of docs/architecture.md, checked on the imports of every module (AST, imports inside functions and
under TYPE_CHECKING included): who may import whom (the packages, and the rooms inside ``hilcal``), no import
cycle, a docstring and at most 550 lines per module, at most 20 modules per folder.
"""

from __future__ import annotations

import ast
import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from scipy.sparse import csr_array
from scipy.sparse.csgraph import connected_components

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("hilcal", "drivers", "procedures", "sim_devices", "benchmarks")
CHECKED_FOR_SIZE = (*PACKAGES, "tests", "tools")
MAX_LINES = 550
WRITTEN_BY_OTHERS = "tests/peers"
"""Test peers written behind an information barrier (tests/peers/__init__.py): kept as their authors wrote them, so
not held to the size rule here."""
MAX_MODULES_PER_FOLDER = 20
"""A folder with more modules than this needs rooms (sub-packages by job); ``__init__.py`` does not count."""
SIM_MAY_USE_FROM_HILCAL = ("hilcal", "hilcal.robot", "hilcal.protocols", "hilcal.recording")
"""The simulators share the robot file, the declarative protocol definitions and the recording format with the
core, never the models that hilcal fits (a simulation must not agree with the tool by construction)."""


@dataclass(frozen=True)
class Edge:
    source: str
    target: str
    where: str  # file:line of the import statement


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))}


MODULES = _modules()


def _targets(name: str, path: Path, node: ast.Import | ast.ImportFrom) -> list[str]:
    """The project modules one import statement executes (the package __init__ files on the way included)."""
    wanted: list[str] = []
    if isinstance(node, ast.Import):
        wanted = [alias.name for alias in node.names]
    else:
        if node.level:
            package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
            base = ".".join(package[: len(package) - node.level + 1] + ([node.module] if node.module else []))
        else:
            base = node.module or ""
        wanted = [f"{base}.{alias.name}" for alias in node.names] + [base]
    # The packages that hold the importing module are already initialised when it runs: no edge to them.
    enclosing = {".".join(name.split(".")[:k]) for k in range(1, name.count(".") + 1)}
    out = []
    for full in wanted:
        top = full.split(".")[0]
        folder = name.rsplit(".", 1)[0]
        if top not in PACKAGES and name.startswith("benchmarks") and f"{folder}.{top}" in MODULES:
            full = f"{folder}.{full}"  # a benchmark script importing a sibling script (`from _docs import ...`)
        parts = full.split(".")
        out += [m for m in (".".join(parts[:k]) for k in range(1, len(parts) + 1)) if m in MODULES
                and m not in enclosing]
    return out


@functools.cache
def _edges() -> list[Edge]:
    """Every import edge between the project's modules (parsed once per process, when a test first asks)."""
    edges = set()
    for name, path in MODULES.items():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import | ast.ImportFrom):
                where = f"{path.relative_to(ROOT)}:{node.lineno}"
                edges.update(Edge(name, t, where) for t in _targets(name, path, node) if t != name)
    return sorted(edges, key=lambda e: (e.where, e.target))



def _layer(module: str) -> str:
    if module == "procedures.cli" or module.startswith("procedures.cli."):
        return "cli"
    return module.split(".")[0]


MAY_IMPORT = {
    "hilcal": {"hilcal"},
    "drivers": {"hilcal", "drivers"},
    "sim_devices": {"hilcal", "sim_devices"},
    "procedures": {"hilcal", "drivers", "procedures"},
    "cli": {"hilcal", "drivers", "procedures", "sim_devices", "cli"},
    "benchmarks": {"hilcal", "drivers", "procedures", "sim_devices", "cli", "benchmarks"},
}


def test_the_graph_sees_the_imports_it_must_see() -> None:
    """The checker itself: known imports (top level, inside functions, relative to a sibling script) are found."""
    found = {(e.source, e.target) for e in _edges()}
    assert ("procedures.runner", "procedures.engine") in found
    assert ("procedures.cli.operator", "procedures.runner") in found  # imported inside `run`
    assert ("benchmarks.bench_cmm", "benchmarks._docs") in found
    assert ("drivers.controller.hilcal_can", "hilcal.protocols") in found
    assert len(MODULES) > 60


def test_each_layer_imports_only_the_layers_below_it() -> None:
    bad = [f"{e.where}: {e.source} ({_layer(e.source)}) imports {e.target} ({_layer(e.target)})"
           for e in _edges() if _layer(e.target) not in MAY_IMPORT[_layer(e.source)]]
    assert not bad, "imports against the layers of docs/architecture.md:\n" + "\n".join(bad)


HILCAL_ROOMS = ("planning", "discovery", "acceptance", "importing", "acquisition", "reports", "protocols", "data")
"""Sub-packages of ``hilcal`` by job; every other module of ``hilcal`` is the calibration math at its top."""
ROOM_MAY_IMPORT = {
    "calibration": {"calibration"},
    "planning": {"calibration", "planning"},
    "discovery": {"calibration", "discovery"},
    "importing": {"calibration", "importing"},
    "acquisition": {"calibration", "acquisition"},
    "acceptance": {"calibration", "planning", "acceptance"},
    "reports": {"calibration", "planning", "discovery", "acceptance", "reports"},
    "protocols": {"protocols"},
    "data": {"data"},
}
"""Inside ``hilcal``: planning and discovery build on the calibration math and never on each other or the reports;
acceptance (ISO 9283, uncertainty, verdict) builds on the math and planning; the reports may show all of them;
importing (`hilcal import`) and acquisition (measuring the machine as it is, during a run) build on the math alone and
no room imports them; the math imports none of the rooms."""


def _room(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in HILCAL_ROOMS else "calibration"


def test_rooms_inside_hilcal_import_only_what_they_may() -> None:
    bad = [f"{e.where}: {e.source} ({_room(e.source)}) imports {e.target} ({_room(e.target)})" for e in _edges()
           if _layer(e.source) == _layer(e.target) == "hilcal"
           and _room(e.target) not in ROOM_MAY_IMPORT[_room(e.source)]]
    assert not bad, "imports against the rooms of hilcal (docs/architecture.md):\n" + "\n".join(bad)


def test_the_room_check_sees_a_forbidden_import() -> None:
    """The room rule on known edges, so the test above can fail: reports may show discovery, not the reverse."""
    assert "discovery" in ROOM_MAY_IMPORT[_room("hilcal.reports.diagnosis")]
    assert "reports" not in ROOM_MAY_IMPORT[_room("hilcal.discovery.search")]
    assert "planning" not in ROOM_MAY_IMPORT[_room("hilcal.discovery.augmentation")]
    assert _room("hilcal.robot") == "calibration" and _room("hilcal.protocols.ippdme") == "protocols"
    found = {(e.source, e.target) for e in _edges()}
    assert ("hilcal.reports.diagnosis", "hilcal.discovery.result") in found
    assert ("hilcal.discovery.search", "hilcal.discovery") not in found  # its own package is already loaded


def test_simulators_share_only_declarative_definitions_with_the_core() -> None:
    bad = [f"{e.where}: {e.source} imports {e.target}" for e in _edges()
           if _layer(e.source) == "sim_devices" and _layer(e.target) == "hilcal"
           and not any(e.target == m or e.target.startswith(m + ".") for m in SIM_MAY_USE_FROM_HILCAL[1:])
           and e.target != "hilcal"]
    assert not bad, "sim_devices may use hilcal's robot, protocols and recording format only:\n" + "\n".join(bad)


def test_no_import_cycle() -> None:
    names = sorted(MODULES)
    index = {n: k for k, n in enumerate(names)}
    rows = [index[e.source] for e in _edges()]
    cols = [index[e.target] for e in _edges()]
    graph = csr_array((np.ones(len(rows)), (rows, cols)), shape=(len(names), len(names)))
    n_components, labels = connected_components(graph, directed=True, connection="strong")
    sizes = np.bincount(labels, minlength=n_components)
    cycles = []
    for component in np.flatnonzero(sizes > 1):
        members = {names[k] for k in np.flatnonzero(labels == component)}
        inside = [f"  {e.where}: {e.source} -> {e.target}" for e in _edges()
                  if e.source in members and e.target in members]
        cycles.append(f"cycle through {', '.join(sorted(members))}:\n" + "\n".join(inside))
    assert not cycles, "\n".join(cycles)


def test_cycle_check_finds_a_cycle() -> None:
    """The strong-component check on a three-module loop, so the test above can fail."""
    graph = csr_array((np.ones(3), ([0, 1, 2], [1, 2, 0])), shape=(4, 4))
    n_components, labels = connected_components(graph, directed=True, connection="strong")
    assert n_components == 2 and len(set(labels[:3])) == 1


@pytest.mark.parametrize("folder", CHECKED_FOR_SIZE)
def test_every_module_is_small_and_says_its_job(folder: str) -> None:
    problems = []
    for path in sorted((ROOT / folder).rglob("*.py")):
        rel = str(path.relative_to(ROOT))
        text = path.read_text()
        n_lines = len(text.splitlines())
        if n_lines > MAX_LINES and not rel.startswith(WRITTEN_BY_OTHERS):
            problems.append(f"{rel}: {n_lines} lines (at most {MAX_LINES}; split it along its jobs)")
        if not (ast.get_docstring(ast.parse(text)) or "").strip():
            problems.append(f"{rel}: no module docstring saying its one job")
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("folder", CHECKED_FOR_SIZE)
def test_no_folder_is_a_crowd(folder: str) -> None:
    crowded = []
    for directory in sorted({p.parent for p in (ROOT / folder).rglob("*.py")}):
        n = sum(1 for p in directory.glob("*.py") if p.name != "__init__.py")
        if n > MAX_MODULES_PER_FOLDER:
            crowded.append(f"{directory.relative_to(ROOT)}: {n} modules (at most {MAX_MODULES_PER_FOLDER}; add rooms)")
    assert not crowded, "\n".join(crowded)
