"""The product's import boundaries (docs/architecture.md, the cell layer): no module of ``pipeline/``,
``drivers/``, ``daemon/`` or ``config/`` imports the simulator (the device registry names its classes as
data), and ``config/`` imports nothing of the package but itself. Every import statement counts, also one
inside a function."""

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
                if sim or outside_config:
                    found.append(f"{path.relative_to(root)}: imports {name}")
    return found


def test_product_never_imports_the_simulator_and_config_imports_nothing_of_the_package():
    assert boundary_violations(PACKAGE_ROOT) == []


def test_a_planted_violation_is_found(tmp_path):
    for area in PRODUCT:
        (tmp_path / area).mkdir()
    (tmp_path / "daemon" / "clean.py").write_text("from tandemscan.drivers.factory import ROLES\n")
    (tmp_path / "daemon" / "planted.py").write_text(
        "def build():\n    from tandemscan.sim_drivers.world import SimWorld\n    return SimWorld\n")
    (tmp_path / "drivers" / "relative.py").write_text("from ..sim_drivers import twins\n")
    (tmp_path / "pipeline" / "plain.py").write_text("import tandemscan.sim_drivers\n")
    (tmp_path / "config" / "models.py").write_text("from tandemscan.pipeline import frames\n"
                                                   "from tandemscan.config.loader import load_config\n")
    assert boundary_violations(tmp_path) == [
        "pipeline/plain.py: imports tandemscan.sim_drivers",
        "drivers/relative.py: imports tandemscan.sim_drivers",
        "drivers/relative.py: imports tandemscan.sim_drivers.twins",
        "daemon/planted.py: imports tandemscan.sim_drivers.world",
        "daemon/planted.py: imports tandemscan.sim_drivers.world.SimWorld",
        "config/models.py: imports tandemscan.pipeline",
        "config/models.py: imports tandemscan.pipeline.frames",
    ]
