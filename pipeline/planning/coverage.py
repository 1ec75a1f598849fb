"""Coverage dry run: which part of the surface (by mesh area) the plan's scans would see, and what it leaves out.

Each planned scanner pose the tracker sees is ray cast with the scanner model (working range and incidence
limit, no noise) at a reduced pixel grid; a triangle counts as seen when a kept ray lands on it. Unseen area is
sorted by reason, after the nearest raster cell: no scanner pose fits (it faces the floor, z = 0 of the part
frame, so steeply and so low that the sweet spot lies under the floor clearance: a part on supports keeps its
underside), out of the arm's reach (the cell has no joint solution), outside the tracker's view (the cell's
pose is reachable but no tracker station sees its target), or missed (between scans or occluded). Each reason
is listed per AGV station with its area, height range and centroid. :class:`CoverageFigures` is what a job's
report.json (``coverage``) and report.html say of it: the planned and measured shares of the surface where a
pose fits and the areas left out (docs/planning.md, "Coverage").
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree
from tandemscan.pipeline.geometry.raycast import ScannerModel
from tandemscan.pipeline.planning.arm import StationRaster
from tandemscan.pipeline.planning.floor import floor_z_mm, no_pose_fits
from tandemscan.pipeline.planning.plan import LeftOutArea, Plan

_DRY_RUN_PIXELS = (64, 50)
_DRY_RUN_POSES_PER_CAST = 128  # poses ray cast together (128 x 3200 rays, about 40 MB)


@dataclass(frozen=True)
class LeftOut:
    """Unseen surface of one kind near one AGV station (-1: no station near): area (mm^2), height range (mm),
    centroid (F, mm)."""

    reason: str
    station: int
    area_mm2: float
    z_range_mm: tuple[float, float]
    centroid_mm: tuple[float, float, float]


@dataclass(frozen=True)
class CoverageReport:
    """Areas in mm^2; ``coverage_pct`` of the whole surface less what faces the floor with no room for a pose."""

    total_area_mm2: float
    floor_contact_mm2: float
    seen_area_mm2: float
    unreachable_mm2: float
    untracked_mm2: float
    missed_mm2: float
    left_out: tuple[LeftOut, ...]

    @property
    def coverage_pct(self) -> float:
        """Seen share of the surface where a scanner pose fits at all (%)."""
        visible = self.total_area_mm2 - self.floor_contact_mm2
        return 100.0 * self.seen_area_mm2 / visible if visible > 0 else 0.0

    @property
    def coverage_of_reachable_pct(self) -> float:
        """Seen share of the surface a scanner on the arm can reach (not on the floor, not out of reach) (%)."""
        reach = self.seen_area_mm2 + self.missed_mm2 + self.untracked_mm2
        return 100.0 * self.seen_area_mm2 / reach if reach > 0 else 0.0

    @property
    def coverage_of_all_pct(self) -> float:
        """Seen share of the whole mesh surface, the floor-facing underside included (%)."""
        return 100.0 * self.seen_area_mm2 / self.total_area_mm2 if self.total_area_mm2 > 0 else 0.0

    def as_dict(self) -> dict:
        return {
            "coverage_pct": round(self.coverage_pct, 2),
            "coverage_of_reachable_pct": round(self.coverage_of_reachable_pct, 2),
            "coverage_of_all_pct": round(self.coverage_of_all_pct, 2),
            "total_area_m2": round(self.total_area_mm2 / 1e6, 3),
            "seen_area_m2": round(self.seen_area_mm2 / 1e6, 3),
            "floor_contact_m2": round(self.floor_contact_mm2 / 1e6, 3),
            "unreachable_m2": round(self.unreachable_mm2 / 1e6, 3),
            "outside_tracker_view_m2": round(self.untracked_mm2 / 1e6, 3),
            "missed_m2": round(self.missed_mm2 / 1e6, 3),
            "left_out": [a.model_dump() for a in self.left_out_areas()],
        }

    def left_out_areas(self) -> list[LeftOutArea]:
        """The left-out areas as the plan file records them (m^2, mm)."""
        return [LeftOutArea(reason=lo.reason, station=lo.station, area_m2=round(lo.area_mm2 / 1e6, 4),
                            z_range_mm=tuple(round(v) for v in lo.z_range_mm),
                            centroid_mm=tuple(round(v) for v in lo.centroid_mm)) for lo in self.left_out]


def seen_triangles(
    mesh: o3d.geometry.TriangleMesh,
    scene: o3d.t.geometry.RaycastingScene,
    poses_T_F_S: list[np.ndarray],
    scanner: ScannerModel,
) -> np.ndarray:
    """Boolean per triangle: some planned scan sees it (``scanner``'s range and incidence limits, at a reduced
    pixel grid)."""
    model = scanner.with_pixels(_DRY_RUN_PIXELS)
    seen = np.zeros(len(mesh.triangles), bool)
    for start in range(0, len(poses_T_F_S), _DRY_RUN_POSES_PER_CAST):
        seen[model.seen_primitives(scene, np.array(poses_T_F_S[start:start + _DRY_RUN_POSES_PER_CAST]))] = True
    return seen


def triangle_geometry(mesh: o3d.geometry.TriangleMesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per triangle: area (mm^2), outward unit normal and centroid (F, mm), whatever the mesh's winding."""
    p = np.asarray(mesh.vertices)[np.asarray(mesh.triangles)]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    if np.einsum("ij,ij->i", p[:, 0], cross).sum() < 0:  # inward winding: turn the normals outward
        cross = -cross
    area = 0.5 * np.linalg.norm(cross, axis=1)
    return area, cross / np.maximum(2 * area, 1e-12)[:, None], p.mean(axis=1)


def pose_fits(mesh: o3d.geometry.TriangleMesh, sweet_spot_mm: float, incidence_limit_rad: float) -> np.ndarray:
    """Per triangle: some scanner pose within the incidence limit fits above the floor clearance (the surface
    the coverage figures count)."""
    _, normal, centroid = triangle_geometry(mesh)
    return ~no_pose_fits(centroid, normal, _floor_z(mesh), sweet_spot_mm, incidence_limit_rad)


def _floor_z(mesh: o3d.geometry.TriangleMesh) -> float:
    return floor_z_mm(float(np.asarray(mesh.vertices)[:, 2].min()))


COVERAGE_OF = "surface where a pose fits"


@dataclass(frozen=True)
class CoverageFigures:
    """A job's coverage as report.json (``coverage``) and report.html state it: the shares (%) of the part's
    surface where a scanner pose fits (``pose_fits``, per CAD triangle: :func:`pose_fits`) that the plan sees
    (``planned_pct``; None: a plan that does not state it) and that the cloud measured (``measured_pct``: CAD
    triangles with a cloud point within 1 mm, ``deviation_maps.measured_triangles``; None: no cloud aligned to
    CAD), and the areas the plan leaves out (part frame F, mm)."""

    planned_pct: float | None
    left_out: tuple[LeftOutArea, ...]
    measured_pct: float | None = None
    pose_fits: np.ndarray | None = field(default=None, repr=False, compare=False)

    @classmethod
    def of_plan(cls, plan: Plan, mesh: o3d.geometry.TriangleMesh, sweet_spot_mm: float,
                incidence_limit_rad: float) -> CoverageFigures:
        """What ``plan`` states (its coverage and left-out areas) and where a pose fits on ``mesh``."""
        return cls(plan.coverage_pct, tuple(plan.left_out), None,
                   pose_fits(mesh, sweet_spot_mm, incidence_limit_rad))

    def with_measured(self, mesh: o3d.geometry.TriangleMesh, measured: np.ndarray) -> CoverageFigures:
        """These figures with ``measured_pct`` from ``measured`` (per triangle of ``mesh``, the CAD mesh
        ``pose_fits`` was found on); unchanged where that is not known or the meshes differ."""
        measured = np.asarray(measured, bool)
        if self.pose_fits is None or len(self.pose_fits) != len(measured):
            return self
        area, _, _ = triangle_geometry(mesh)
        total = float(area[self.pose_fits].sum())
        share = 100.0 * float(area[self.pose_fits & measured].sum()) / total if total > 0 else 0.0
        return replace(self, measured_pct=round(share, 2))

    def as_dict(self) -> dict:
        """report.json's ``coverage``: each left-out area with its reason, area (m^2) and where it is in words
        (with its centroid and height range, mm, for a script)."""
        return {"planned_pct": self.planned_pct, "measured_pct": self.measured_pct, "of": COVERAGE_OF,
                "left_out": [{"reason": a.reason, "area_m2": a.area_m2, "where": _where(a),
                              "centroid_mm": list(a.centroid_mm), "z_range_mm": list(a.z_range_mm)}
                             for a in self.left_out]}


def _where(area: LeftOutArea) -> str:
    x, y, z = area.centroid_mm
    near = f"near AGV station {area.station}" if area.station >= 0 else "near no AGV station"
    return (f"{near}, z {area.z_range_mm[0]:.0f} to {area.z_range_mm[1]:.0f} mm, centred at x {x:.0f}, y {y:.0f}, "
            f"z {z:.0f} mm")


REASON_NO_POSE = "faces the floor: no room for a scanner pose"
REASON_REACH = "out of the arm's reach"
REASON_TRACKER = "outside the tracker's view"
REASON_MISSED = "missed between scans or occluded"


def dry_run(
    mesh: o3d.geometry.TriangleMesh,
    scene: o3d.t.geometry.RaycastingScene,
    rasters: list[StationRaster],
    scanner: ScannerModel,
    incidence_limit_rad: float,
    tracked: np.ndarray | None = None,
) -> CoverageReport:
    """Coverage of the plan's scans by mesh area, with the unseen area attributed to a reason and a station.

    ``tracked[i]`` (default: all): the tracker sees the target at the i-th pose of ``rasters`` (in raster
    order); the poses it does not see are not scanned and their surface is "outside the tracker's view".
    """
    tri = np.asarray(mesh.triangles)
    p = np.asarray(mesh.vertices)[tri]
    area, normal, centroid = triangle_geometry(mesh)
    poses = [ps for r in rasters for ps in r.poses]
    tracked = np.ones(len(poses), bool) if tracked is None else np.asarray(tracked, bool)
    seen = seen_triangles(mesh, scene, [ps.T_F_S for ps, ok in zip(poses, tracked, strict=True) if ok], scanner)

    cell_pts, cell_reason, cell_station = [], [], []
    for ps, ok in zip(poses, tracked, strict=True):
        cell_pts.append(ps.cell.point_F)
        cell_reason.append(REASON_MISSED if ok else REASON_TRACKER)
        cell_station.append(ps.station)
    for r in rasters:
        for u in r.unreached:
            cell_pts.append(u.cell.point_F)
            cell_reason.append(REASON_REACH)
            cell_station.append(r.station.index)
    reason = np.full(len(tri), "", dtype=object)
    station = np.full(len(tri), -1)
    unseen = ~seen
    if cell_pts and unseen.any():
        _, nearest = cKDTree(np.array(cell_pts)).query(centroid[unseen])
        reason[unseen] = np.array(cell_reason, dtype=object)[nearest]
        station[unseen] = np.array(cell_station)[nearest]
    else:
        reason[unseen] = REASON_REACH
    no_pose = no_pose_fits(centroid, normal, _floor_z(mesh), scanner.sweet_spot_mm, incidence_limit_rad)
    reason[no_pose & unseen] = REASON_NO_POSE
    left = []
    for why in (REASON_NO_POSE, REASON_REACH, REASON_TRACKER, REASON_MISSED):
        for st in np.unique(station[reason == why]):
            sel = (reason == why) & (station == st)
            a = float(area[sel].sum())
            left.append(LeftOut(why, int(st), a, (float(p[sel][:, :, 2].min()), float(p[sel][:, :, 2].max())),
                                tuple(float(c) for c in (area[sel] @ centroid[sel]) / a)))
    left.sort(key=lambda lo: -lo.area_mm2)
    return CoverageReport(
        float(area.sum()), float(area[reason == REASON_NO_POSE].sum()), float(area[seen].sum()),
        float(area[reason == REASON_REACH].sum()), float(area[reason == REASON_TRACKER].sum()),
        float(area[reason == REASON_MISSED].sum()), tuple(left),
    )
