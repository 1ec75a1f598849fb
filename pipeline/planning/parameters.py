"""The planning stages' parameters: small frozen objects of what each stage uses (mm, rad), built once from the
cell's configuration where it is read (:meth:`PartPlanning.from_config`, in the daemon, a command or a benchmark),
so that the stages never see a whole configuration section (docs/planning.md, "Parameters").

The configuration's degrees become radians here, once. The arm stays its ``[arm]`` section (``ArmConfig``): its
kinematics and limits are the arm's description, shared with the IK and the daemon.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from tandemscan.config.models import ArmConfig
from tandemscan.pipeline.geometry.raycast import ScannerModel


@dataclass(frozen=True)
class ScanFootprint:
    """One scan as the raster lays it out: ``sweet_spot_mm`` the distance from the scanner to the surface along
    the view; ``width_mm`` (``m``) and ``height_mm`` (``n``) the useful patch at the sweet spot along and across
    the contour, the overlap with its neighbours taken off (Eq. 15, mm); ``incidence_limit_rad`` the steepest
    view of the surface a pose may take (the tighter of ``[planning]``'s and the scanner's limits, rad)."""

    sweet_spot_mm: float
    width_mm: float
    height_mm: float
    incidence_limit_rad: float


@dataclass(frozen=True)
class StationSpacing:
    """Where the measurement AGV's stations go (Eq. 13-14): the arm's standoff from the contour ``d3`` to ``d4``
    (mm), the chassis width ``w`` (mm), the least station step ``p`` (mm), and the floor a chassis may stand on:
    the cell's rectangle (x min, y min, x max, y max) less the keep-out polygons (part frame F, xy mm)."""

    arm_standoff_min_mm: float
    arm_standoff_max_mm: float
    agv_width_mm: float
    station_step_mm: float
    floor_xy_mm: tuple[float, float, float, float]
    keep_out_xy_mm: tuple[tuple[tuple[float, float], ...], ...] = ()


@dataclass(frozen=True)
class AgvMargin:
    """How far the AGV may stand off its station and a planned pose must stay reachable: ``distance_mm``
    forward, back and sideways, ``heading_rad`` either way round."""

    distance_mm: float
    heading_rad: float


@dataclass(frozen=True)
class TrackerCandidates:
    """Where the tracking AGV may stand: on the contour's outward offset by ``distance_mm``, every
    ``spacing_mm``, turned from facing the part by each of ``heading_offsets_rad``."""

    distance_mm: float
    spacing_mm: float
    heading_offsets_rad: tuple[float, ...]


@dataclass(frozen=True)
class TrackerView:
    """What the tracker sees of a target from a station, a margin for chassis slip taken off its limits: the half
    fields of view about its camera's x and y axes (rad), the target's view cone (rad) and the range (mm)."""

    half_fov_horizontal_rad: float
    half_fov_vertical_rad: float
    view_cone_rad: float
    range_min_mm: float
    range_max_mm: float


@dataclass(frozen=True)
class ChainLimits:
    """How long (s) and how large (variables) an exact tracker-chain integer program may be; else the greedy
    chain stands."""

    time_limit_s: float
    max_variables: int


@dataclass(frozen=True)
class PartPlanning:
    """All :func:`~tandemscan.pipeline.planning.planner.plan_part` uses of the cell: the stages' parameters, the
    arm (DH, limits; ``[arm]``), its joints where a job starts (rad), the lifting column's heights to try (mm above
    the mount; ``(0.0,)`` without one) and whether there is one, the nominal installation transforms (4x4, mm),
    the scanner model the coverage dry run casts with, and the incidence limit that dry run counts (rad)."""

    footprint: ScanFootprint
    spacing: StationSpacing
    margin: AgvMargin
    tracker_candidates: TrackerCandidates
    tracker_view: TrackerView
    chain: ChainLimits
    arm: ArmConfig
    arm_start_rad: np.ndarray
    lift_heights_mm: tuple[float, ...]
    lift_enabled: bool
    T_V2_B: np.ndarray
    T_E_S: np.ndarray
    T_T_S: np.ndarray
    T_V1_C: np.ndarray
    scanner: ScannerModel
    coverage_incidence_limit_rad: float

    @classmethod
    def from_config(cls, config: object) -> PartPlanning:
        """From a cell configuration (``CellConfig``; its ``[planning]``, ``[scanner]``, ``[tracker]``, ``[arm]``,
        ``[lift]`` and ``[installation]`` sections), degrees turned into radians once."""
        pl, scanner, tracker, inst = config.planning, config.scanner, config.tracker, config.installation
        margin = pl.tracker_margin_deg  # chassis slip must not push a target out of view
        return cls(
            footprint=ScanFootprint(
                scanner.sweet_spot_mm, scanner.width_at_sweet_spot_mm * (1.0 - pl.scan_overlap_fraction),
                scanner.height_at_sweet_spot_mm * (1.0 - pl.scan_overlap_fraction),
                math.radians(min(pl.incidence_limit_deg, scanner.max_incidence_deg))),
            spacing=StationSpacing(pl.arm_standoff_min_mm, pl.arm_standoff_max_mm, pl.agv_width_mm,
                                   pl.station_step_mm, tuple(pl.floor_xy_mm), tuple(pl.keep_out_xy_mm)),
            margin=AgvMargin(pl.agv_margin_mm, math.radians(pl.agv_margin_deg)),
            tracker_candidates=TrackerCandidates(pl.tracker_distance_mm, pl.tracker_candidate_step_mm,
                                                 tuple(float(np.radians(o)) for o in pl.tracker_heading_offsets_deg)),
            tracker_view=TrackerView(float(np.radians(tracker.fov_horizontal_deg / 2 - margin)),
                                     float(np.radians(tracker.fov_vertical_deg / 2 - margin)),
                                     float(np.radians(tracker.target_view_cone_deg - margin)),
                                     pl.tracker_min_range_mm, min(pl.tracker_best_range_mm, tracker.range_max_mm)),
            chain=ChainLimits(pl.exact_time_limit_s, pl.exact_max_variables),
            arm=config.arm,
            arm_start_rad=np.radians(pl.arm_start_deg),
            lift_heights_mm=config.lift.heights_mm(),
            lift_enabled=config.lift.enabled,
            T_V2_B=inst.T_V2_B.matrix(), T_E_S=inst.T_E_S.matrix(), T_T_S=inst.T_T_S.matrix(),
            T_V1_C=inst.T_V1_C.matrix(),
            scanner=ScannerModel(scanner),
            coverage_incidence_limit_rad=math.radians(pl.incidence_limit_deg),
        )
