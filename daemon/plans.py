"""The plans a job can name: files shipped in ``tandemscan.config/plans`` and site plans in
``<state dir>/plans`` (TOML or JSON, :class:`tandemscan.pipeline.planning.plan.Plan`), plus the cell's default plan
made on demand by a factory (the planner, for the configured part); and which part a plan is for.

Every plan the catalog hands out has passed its ``check`` (the daemon's: :func:`part_check`, the plan made for the
configured part), so a job cannot be queued with a plan for another part whatever asks for it (docs/daemon.md);
``measure`` refuses such a plan the same way (:func:`check_plan_part`) and plans the configured part when given
none (:func:`plan_configured_part`)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from tandemscan.pipeline.planning.plan import Plan, PlanError

if TYPE_CHECKING:
    from tandemscan.config.models import CellConfig

log = logging.getLogger(__name__)

PLAN_SUFFIXES = (".toml", ".json")
#: what checks a plan file before a job may run it: raises :class:`PlanError` with the reason
PlanCheck = Callable[[Plan, Path], None]


class PlanPartError(Exception):
    """The part cannot be planned, or a plan does not belong to the part (one line for the operator)."""


def part_name(config: CellConfig) -> str:
    """How a plan names its part: the mesh file, or the parametric nose."""
    return str(config.part.mesh) if config.part.mesh else "parametric train nose"


def plan_configured_part(config: CellConfig, name: str):
    """Plan the configured part (mesh file or parametric nose); the tracker chain starts where the tracking robot
    stands (``[planning] tracker_start``). Returns the mesh and the :class:`PartPlan`; raises :class:`PlanPartError`."""
    from tandemscan.pipeline.geometry.part import PartMeshError, load_part_mesh
    from tandemscan.pipeline.geometry.units import extent_mm, small_part_hint
    from tandemscan.pipeline.planning.parameters import PartPlanning
    from tandemscan.pipeline.planning.planner import plan_part
    from tandemscan.pipeline.planning.sequence import SequenceError
    from tandemscan.pipeline.planning.stations import StationPlanningError
    from tandemscan.pipeline.planning.tracker import TrackerPlanningError

    start = config.planning.tracker_start
    try:
        mesh = load_part_mesh(config.part)
    except PartMeshError as e:
        raise PlanPartError(str(e)) from e
    try:
        return mesh, plan_part(mesh, PartPlanning.from_config(config),
                               tracker_start=(start.x_mm, start.y_mm, np.radians(start.heading_deg)),
                               name=name, part=part_name(config))
    except (StationPlanningError, TrackerPlanningError, SequenceError) as e:  # a part read in the wrong unit?
        hint = small_part_hint(extent_mm(np.asarray(mesh.vertices)), "--part-units")
        raise PlanPartError(f"{e}; {hint}" if hint else str(e)) from e


def check_plan_part(plan: Plan, plan_file: Path, config: CellConfig) -> None:
    """Refuse a plan made for another part than the configured mesh (raises :class:`PlanPartError`); a plan that
    does not state its part (older files) is taken as it is."""
    from tandemscan.pipeline.geometry.part import PartMeshError, load_part_mesh, part_identity

    if plan.part_identity is None:
        return
    try:
        mine = part_identity(load_part_mesh(config.part))
    except PartMeshError as e:
        raise PlanPartError(str(e)) from e
    made_for = plan.part_identity
    if mine.sha256 != made_for.sha256:
        raise PlanPartError(
            f"{plan_file}: plan made for another part ({plan.part or 'unnamed'}, bbox {list(made_for.bbox_min_mm)} .. "
            f"{list(made_for.bbox_max_mm)} mm, sha256 {made_for.sha256[:12]}) than {part_name(config)} (bbox "
            f"{list(mine.bbox_min_mm)} .. {list(mine.bbox_max_mm)} mm, sha256 {mine.sha256[:12]}); plan this part "
            "with `tandemscan plan --part MESH` or run `measure --part MESH` without --plan")


def default_plan_path() -> Path:
    """The shipped plan for the default part."""
    return PlanCatalog.shipped_folder() / "default-band.toml"


def part_check(config: CellConfig) -> PlanCheck:
    """:func:`check_plan_part` against ``config``'s part, a mismatch as a :class:`PlanError` naming both parts."""
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
