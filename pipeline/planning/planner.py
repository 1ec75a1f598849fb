"""Plan a whole part: AGV stations, arm rasters, tracker stations and the command sequence (docs/planning.md).

Everything is in the part frame F (mm, rad). The cell comes as a :class:`PartPlanning` built once from the
configuration; its installation transforms are the nominal (or calibrated) ones, never the simulator's truth.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from shapely.geometry import Point
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.part import part_identity
from tandemscan.pipeline.geometry.raycast import make_scene
from tandemscan.pipeline.planning.arm import ArmSetup, IkSolver, ScanPose, StationRaster, plan_arm
from tandemscan.pipeline.planning.coverage import CoverageReport, dry_run
from tandemscan.pipeline.planning.ik import default_ik
from tandemscan.pipeline.planning.parameters import PartPlanning, StationSpacing, TrackerCandidates
from tandemscan.pipeline.planning.sequence import PoseRef, Sequence, build_sequence
from tandemscan.pipeline.planning.stations import StationLayout, free_floor, offset_ring, place_stations
from tandemscan.pipeline.planning.tracker import TrackerSolution, candidate_poses, choose_stations, cover_matrix

log = logging.getLogger(__name__)


@dataclass
class PartPlan:
    """Everything the planner decided, for the plan file, the picture, the coverage check and the benchmark."""

    layout: StationLayout
    rasters: list[StationRaster]
    poses: list[ScanPose]
    candidates: np.ndarray  # (K, 3) tracker candidates: x mm, y mm, heading rad
    cover: np.ndarray  # (K, M) candidate k sees the target at pose m
    tracker: TrackerSolution
    sequence: Sequence
    start_candidate: int | None
    coverage: CoverageReport
    seconds: dict[str, float] = field(default_factory=dict)

    @property
    def tracker_chain(self) -> list[tuple[float, float, float]]:
        """The chain's tracker stations in measuring order: x mm, y mm, heading rad (frame F)."""
        return [tuple(float(v) for v in self.candidates[k]) for k in self.tracker.chain]

    @property
    def cells(self) -> int:
        return sum(len(r.poses) + len(r.unreached) for r in self.rasters)

    def summary(self) -> dict:
        """Counts, solver and timings (JSON-ready)."""
        return {
            "agv_stations": len(self.layout.stations),
            "agv_stations_skipped": len(self.layout.skipped),
            "agv_step_mm": round(self.layout.step_mm, 1),
            "raster_cells": self.cells,
            "scans": self.sequence.plan.scan_count,
            "unreachable_cells": sum(len(r.unreached) for r in self.rasters),
            "poses_without_margin": sum(not p.robust for p in self.poses),
            "poses_unseen_by_tracker": len(self.tracker.uncovered),
            "tracker_candidates": len(self.candidates),
            "tracker_stations": self.tracker.count,
            "tracker_solver": self.tracker.solver,
            "tracker_optimal": self.tracker.optimal,
            "tracker_lower_bound": self.tracker.lower_bound,
            "transfers": self.sequence.plan.transfer_count,
            "lift_moves": sum(s.kind == "move_lift" for s in self.sequence.plan.steps),
            "joint_travel_rad": round(sum(r.joint_travel_rad for r in self.rasters), 2),
            "plan_seconds": round(sum(self.seconds.values()), 3),
            "seconds": {k: round(v, 3) for k, v in self.seconds.items()},
        }


def target_poses(poses: list[ScanPose], T_T_S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Target positions (F, mm) and visible normals (its z axis) at each scan pose."""
    if not poses:
        return np.zeros((0, 3)), np.zeros((0, 3))
    T_F_T = np.stack([p.T_F_S for p in poses]) @ F.invert(T_T_S)
    return T_F_T[:, :3, 3], T_F_T[:, :3, 2]


def tracker_candidates(layout: StationLayout, where: TrackerCandidates, spacing: StationSpacing) -> np.ndarray:
    """Candidate tracking-AGV poses at ``d1`` around the part, on free floor only (``spacing``'s floor and
    chassis width)."""
    ring, inward = offset_ring(layout.contour, where.distance_mm, where.spacing_mm)
    cand = candidate_poses(ring, inward, where.heading_offsets_rad)
    floor = free_floor(spacing)
    half = 0.5 * spacing.agv_width_mm
    ok = [floor.contains(Point(x, y).buffer(half, quad_segs=8)) for x, y, _ in cand]
    return cand[np.array(ok, bool)] if len(cand) else cand


def plan_part(
    mesh: o3d.geometry.TriangleMesh,
    cell: PartPlanning,
    ik: IkSolver | None = None,
    tracker_start: tuple[float, float, float] | None = None,
    name: str = "generated",
    part: str = "",
) -> PartPlan:
    """Plan the measurement of ``mesh`` on the cell ``cell`` (``PartPlanning.from_config(config)``).

    ``tracker_start`` (x mm, y mm, heading rad): where the tracking robot stands when the job begins; the
    chain starts there when it sees any measuring point.
    """
    seconds: dict[str, float] = {}
    t = time.perf_counter()
    layout = place_stations(mesh, cell.spacing, cell.footprint)
    seconds["stations"] = time.perf_counter() - t

    t = time.perf_counter()
    scene = make_scene(mesh)
    bb = mesh.get_axis_aligned_bounding_box()
    home = cell.arm_start_rad
    rasters = plan_arm(scene, (bb.min_bound, bb.max_bound), layout.stations, layout.step_mm,
                       layout.path.exterior.length,
                       ArmSetup(ik or default_ik(cell.arm), cell.arm, cell.T_V2_B, cell.T_E_S, cell.footprint,
                                cell.spacing, cell.margin, cell.lift_heights_mm), home)
    poses = [p for r in rasters for p in r.poses]
    seconds["arm"] = time.perf_counter() - t

    t = time.perf_counter()
    candidates = tracker_candidates(layout, cell.tracker_candidates, cell.spacing)
    start = None
    if tracker_start is not None:
        candidates = np.vstack([candidates, np.asarray(tracker_start, float)[None, :]])
        start = len(candidates) - 1
    pts, nrm = target_poses(poses, cell.T_T_S)
    cover = cover_matrix(candidates, cell.T_V1_C, pts, nrm, scene, cell.tracker_view)
    if start is not None and not cover[start].any():
        log.warning("the tracker's start pose sees none of the planned scans; the plan moves it first")
        start = None
    seconds["tracker_cover"] = time.perf_counter() - t

    t = time.perf_counter()
    solution = choose_stations(cover, cell.chain, first=start)
    seconds["tracker_solve"] = time.perf_counter() - t

    t = time.perf_counter()
    refs = [PoseRef(p.station, (layout.stations[p.station].x_mm, layout.stations[p.station].y_mm,
                                layout.stations[p.station].heading_rad),
                    tuple(float(v) for v in p.joints_rad), f"station {p.station} row {p.cell.row} col {p.cell.col}",
                    p.T_F_S, p.lift_mm if cell.lift_enabled else None)
            for p in poses]
    chain_poses = [tuple(float(v) for v in candidates[k]) for k in solution.chain]
    sequence = build_sequence(refs, chain_poses, cover[list(solution.chain)], home, name, part,
                              tracker_starts_at_first=start is not None)
    seconds["sequence"] = time.perf_counter() - t

    t = time.perf_counter()
    tracked = cover[list(solution.chain)].any(axis=0) if len(solution.chain) else np.zeros(len(poses), bool)
    coverage = dry_run(mesh, scene, rasters, cell.scanner, cell.coverage_incidence_limit_rad, tracked)
    stated = sequence.plan.model_copy(update={"part_identity": part_identity(mesh),
                                              "left_out": coverage.left_out_areas(),
                                              "coverage_pct": round(coverage.coverage_pct, 2)})
    sequence = dataclasses.replace(sequence, plan=stated)
    seconds["coverage"] = time.perf_counter() - t
    plan = PartPlan(layout, rasters, poses, candidates, cover, solution, sequence, start, coverage, seconds)
    log.info("plan: %s", plan.summary())
    return plan
