"""The product's import boundaries (docs/architecture.md, the cell layer): no module of ``pipeline/``,
``drivers/``, ``daemon/`` or ``config/`` imports the simulator (the device registry names its classes as
data), ``config/`` imports nothing of the package but itself, ``pipeline/`` never imports ``daemon/`` (the daemon
calls the pipeline, the pipeline never calls back), and the modules of ``daemon/`` import each other
without a cycle (docs/architecture.md, "The daemon's packages"). Every import statement counts, also one inside a
function or under ``TYPE_CHECKING``."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE_ROOT = Path(__file__).resolve().parents[2]  # the repository root is the package tandemscan
PRODUCT = ("pipeline", "drivers", "daemon", "config")


def imported_modules(source: str, module: str) -> set[str]:
    """Absolute names of every module ``source`` (the module ``module``) imports, relative imports resolved."""
    names = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = module.split(".")[: -node.level]
                base = ".".join([*parent, base] if base else parent)
            names |= {base} | {f"{base}.{a.name}" for a in node.names}
    return names


def boundary_violations(root: Path, package: str = "tandemscan") -> list[str]:
    """``"file: imports module"`` for every import across a boundary in the tree at ``root``."""
    found = []
    for area in PRODUCT:
        for path in sorted((root / area).rglob("*.py")):
            module = ".".join([package, *path.relative_to(root).with_suffix("").parts])
            for name in sorted(imported_modules(path.read_text(encoding="utf-8"), module)):
                sim = name == f"{package}.sim_drivers" or name.startswith(f"{package}.sim_drivers.")
                outside_config = (area == "config" and name.startswith(f"{package}.")
                                  and not name.startswith(f"{package}.config"))
                into_daemon = area == "pipeline" and (name == f"{package}.daemon"
                                                      or name.startswith(f"{package}.daemon."))
                if sim or outside_config or into_daemon:
                    found.append(f"{path.relative_to(root)}: imports {name}")
    return found


def test_product_never_imports_the_simulator_config_nothing_of_the_package_and_pipeline_no_daemon():
    assert boundary_violations(PACKAGE_ROOT) == []


def test_a_planted_violation_is_found(tmp_path):
    for area in PRODUCT:
        (tmp_path / area).mkdir()
    (tmp_path / "daemon" / "clean.py").write_text("from tandemscan.drivers.factory import ROLES\n")
    (tmp_path / "daemon" / "planted.py").write_text(
        "def build():\n    from tandemscan.sim_drivers.world import SimWorld\n    return SimWorld\n")
    (tmp_path / "drivers" / "relative.py").write_text("from ..sim_drivers import twins\n")
    (tmp_path / "pipeline" / "plain.py").write_text("import tandemscan.sim_drivers\n")
    (tmp_path / "pipeline" / "upward.py").write_text("def f():\n    from tandemscan.daemon import finish\n")
    (tmp_path / "config" / "models.py").write_text("from tandemscan.pipeline import frames\n"
                                                   "from tandemscan.config.loader import load_config\n")
    assert boundary_violations(tmp_path) == [
        "pipeline/plain.py: imports tandemscan.sim_drivers",
        "pipeline/upward.py: imports tandemscan.daemon",
        "pipeline/upward.py: imports tandemscan.daemon.finish",
        "drivers/relative.py: imports tandemscan.sim_drivers",
        "drivers/relative.py: imports tandemscan.sim_drivers.twins",
        "daemon/planted.py: imports tandemscan.sim_drivers.world",
        "daemon/planted.py: imports tandemscan.sim_drivers.world.SimWorld",
        "config/models.py: imports tandemscan.pipeline",
        "config/models.py: imports tandemscan.pipeline.frames",
    ]


PLANNING_SECTIONS = ("CellConfig", "PlanningConfig", "ScannerConfig", "TrackerConfig")


def planning_section_imports(root: Path, package: str = "tandemscan") -> list[str]:
    """``"file: imports name"`` for every module of ``pipeline/planning/`` that imports one of the configuration
    sections in :data:`PLANNING_SECTIONS`: the planning stages take small parameter objects built once from the
    configuration (docs/planning.md, "Parameters")."""
    sections = {f"{package}.config.models.{name}" for name in PLANNING_SECTIONS}
    found = []
    for path in sorted((root / "pipeline" / "planning").rglob("*.py")):
        module = ".".join([package, *path.relative_to(root).with_suffix("").parts])
        for name in sorted(imported_modules(path.read_text(encoding="utf-8"), module) & sections):
            found.append(f"{path.relative_to(root).as_posix()}: imports {name}")
    return found


def test_planning_stages_import_no_whole_configuration_section():
    assert planning_section_imports(PACKAGE_ROOT) == []


def test_a_planted_planning_section_import_is_found(tmp_path):
    (tmp_path / "pipeline" / "planning").mkdir(parents=True)
    (tmp_path / "pipeline" / "planning" / "arm.py").write_text("from tandemscan.config.models import ArmConfig\n")
    (tmp_path / "pipeline" / "planning" / "late.py").write_text(
        "def plan():\n    from ...config.models import ArmConfig, PlanningConfig\n")
    assert planning_section_imports(tmp_path) == [
        "pipeline/planning/late.py: imports tandemscan.config.models.PlanningConfig"]


def imported_daemon_modules(source: str, module: str, modules: set[str]) -> set[str]:
    """The modules of ``modules`` that ``source`` (the module ``module``, ``.__init__`` for a package) imports:
    ``from a import b`` is ``a.b`` where that is one of them, else ``a``; ``import a.b`` is ``a.b``; a name that is
    not itself one of them counts as the module that defines it (its longest prefix among them)."""
    def defining(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    found = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found |= {defining(a.name) for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = module.split(".")[: -node.level]
                base = ".".join([*parent, base] if base else parent)
            found |= {f"{base}.{a.name}" if f"{base}.{a.name}" in modules else defining(base) for a in node.names}
    return found - {None}


def daemon_import_graph(root: Path, package: str = "tandemscan") -> dict[str, set[str]]:
    """Module of ``daemon/`` -> the modules of ``daemon/`` it imports (:func:`imported_daemon_modules`; names
    relative to ``daemon``, a package by its own name, ``daemon`` itself ""); importing a module does not count as
    importing the packages above it."""
    daemon = f"{package}.daemon"
    paths = {}
    for path in sorted((root / "daemon").rglob("*.py")):
        parts = path.relative_to(root).with_suffix("").parts
        paths[".".join([package, *(parts[:-1] if parts[-1] == "__init__" else parts)])] = path
    graph = {}
    for module, path in paths.items():
        own = module + (".__init__" if path.name == "__init__.py" else "")
        targets = imported_daemon_modules(path.read_text(encoding="utf-8"), own, set(paths)) - {module, daemon}
        graph[module.removeprefix(daemon).removeprefix(".")] = {t.removeprefix(daemon + ".") for t in targets}
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of ``graph`` with more than one module (each sorted; Tarjan's
    algorithm, iterative): every module of one imports every other, directly or through the others."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles = []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    cycles.append(sorted(component))
    return sorted(cycles)


def test_daemon_modules_import_each_other_without_a_cycle():
    assert import_cycles(daemon_import_graph(PACKAGE_ROOT)) == []


def test_a_planted_import_cycle_is_found(tmp_path):
    (tmp_path / "daemon" / "shop").mkdir(parents=True)
    (tmp_path / "daemon" / "__init__.py").write_text("")
    (tmp_path / "daemon" / "shop" / "__init__.py").write_text("")
    (tmp_path / "daemon" / "shop" / "till.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .ledger import Ledger\n")
    (tmp_path / "daemon" / "shop" / "ledger.py").write_text(
        "def take():\n    from tandemscan.daemon.shop import till\n    return till\n")
    (tmp_path / "daemon" / "alone.py").write_text("from tandemscan.daemon.shop.till import Till\n")
    graph = daemon_import_graph(tmp_path)
    assert graph == {"": set(), "shop": set(), "shop.till": {"shop.ledger"}, "shop.ledger": {"shop.till"},
                     "alone": {"shop.till"}}
    assert import_cycles(graph) == [["shop.ledger", "shop.till"]]
