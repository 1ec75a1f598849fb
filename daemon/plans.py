"""The plans a job can name: files shipped in ``tandemscan.config/plans`` and site plans in
``<state dir>/plans`` (TOML or JSON, :class:`tandemscan.pipeline.planning.plan.Plan`), plus the cell's default plan
made on demand by a factory (the planner, for the configured part).

Every plan the catalog hands out has passed its ``check`` (the daemon's: :func:`part_check`, the plan made for the
configured part), so a job cannot be queued with a plan for another part whatever asks for it (docs/daemon.md)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

from tandemscan.pipeline.planning.plan import Plan, PlanError

if TYPE_CHECKING:
    from tandemscan.config.models import CellConfig

log = logging.getLogger(__name__)

PLAN_SUFFIXES = (".toml", ".json")
#: what checks a plan file before a job may run it: raises :class:`PlanError` with the reason
PlanCheck = Callable[[Plan, Path], None]


def part_check(config: CellConfig) -> PlanCheck:
    """The CLI's :func:`~tandemscan.daemon.cli.plan_cmd.check_plan_part` against ``config``'s part, a mismatch as a
    :class:`PlanError` naming both parts."""
    from tandemscan.daemon.cli.plan_cmd import PlanPartError, check_plan_part

    def check(plan: Plan, plan_file: Path) -> None:
        try:
            check_plan_part(plan, plan_file, config)
        except PlanPartError as e:
            raise PlanError(str(e)) from e

    return check


class PlanCatalog:
    """Named plans. ``default_name`` is what an empty job request gets; ``default_factory()`` makes it
    when no file of that name exists (cached after the first call). ``check`` (when given) vets every plan file
    :meth:`get` loads."""

    def __init__(self, folders: Iterable[Path], default_name: str = "default-band",
                 default_factory: Callable[[], Plan] | None = None, check: PlanCheck | None = None):
        self.folders = [Path(f) for f in folders]
        self.default_name = default_name
        self._default_factory = default_factory
        self._check = check
        self._default: Plan | None = None

    @staticmethod
    def shipped_folder() -> Path:
        return Path(str(resources.files("tandemscan.config").joinpath("plans")))

    def _files(self) -> dict[str, Path]:
        found: dict[str, Path] = {}
        for folder in self.folders:
            if folder.is_dir():
                for f in sorted(folder.iterdir()):
                    if f.suffix in PLAN_SUFFIXES:
                        found[f.stem] = f  # later folders (site) override earlier ones (shipped)
        return found

    def names(self) -> list[str]:
        names = set(self._files())
        if self._default_factory is not None:
            names.add(self.default_name)
        return sorted(names)

    def get(self, name: str | None) -> Plan:
        """The plan called ``name`` (None: the default); raises :class:`PlanError` when unknown, invalid or refused
        by the catalog's check."""
        name = name or self.default_name
        files = self._files()
        if name in files:
            plan = Plan.load(files[name])
            if self._check is not None:
                self._check(plan, files[name])
            return plan
        if name == self.default_name and self._default_factory is not None:
            if self._default is None:
                self._default = self._default_factory()
            return self._default
        raise PlanError(f"no plan named {name!r}; known: {', '.join(self.names()) or 'none'}")

    def summaries(self) -> list[dict]:
        """One line per plan: name, part, number of steps, scans and transfers (invalid files say why)."""
        out = []
        for name in self.names():
            try:
                p = self.get(name)
            except PlanError as e:
                out.append({"name": name, "valid": False, "error": str(e)})
                continue
            out.append({"name": name, "valid": True, "part": p.part, "steps": len(p.steps),
                        "scans": p.scan_count, "transfers": p.transfer_count, "default": name == self.default_name})
        return out
