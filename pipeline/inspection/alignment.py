"""Registration of a measured cloud's frame W (the job's world, or whatever frame a cloud file is in) to
the CAD frame F, from what was measured: no ground truth (docs/inspection-method.md, "Alignment").

- **Stations** (coarse, to centimetres): the plan places the measurement AGV's stations in F; the job
  measures where the AGV stood in W (Eq. 5). A least-squares rigid fit of the two gives ``T_F_W``.
- **Best fit**: trimmed point-to-plane ICP against the mesh itself from coarse to fine trim distances (from
  400 mm: a cloud given 20 deg and 200 mm off CAD reaches the same fit), then a Huber-weighted pass,
  optionally with the points of named datum regions only.
- **RPS**: reference spheres with calibrated CAD centres are fitted in the cloud (the calibration's sphere
  fit) where a best fit (the pre-alignment) places them; ``T_F_W`` is the least-squares fit of the centres
  alone, with a residual per sphere. A best fit spreads a warp over the whole part; RPS leaves it where
  it is.

All mm, 4x4 float64 ``T_a_b`` (frame b into frame a); angles in radians except the report's ``*_deg``.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
from tandemscan.pipeline.calibration.plate import PlateError, fit_sphere
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.units import extent_mm, scale_mismatch
from tandemscan.pipeline.inspection.cad_orientation import wind
from tandemscan.pipeline.inspection.inspect import (
    CadSurface,
    InspectionError,
    SeenFrom,
    SurfaceFit,
    as_points,
    best_fit,
    region_mask,
)
from tandemscan.pipeline.parameters import FromSection
from tandemscan.pipeline.planning.plan import MoveMeasure, Plan, Scan
from tandemscan.pipeline.registration.global_registration import FeatureMatching, fpfh_ransac

if TYPE_CHECKING:
    from tandemscan.config.models import ReferenceSphereConfig, RegionConfig

log = logging.getLogger(__name__)

OFF_SURFACE_MM = 1.0  # a point this far off the CAD surface near a sphere's place may lie on the sphere
STATION_ARM_MM = 1000.0  # a station pose enters the fit as its origin and points this far along its x and y


@dataclass(frozen=True)
class AlignmentCriteria(FromSection):
    """How a cloud is aligned to CAD: ``[inspection]``'s keys of the same names
    (``AlignmentCriteria.from_section(cfg)``; mm). The method (``alignment``: best-fit, rps or none); the best
    fit's trim distances (``alignment_distances_mm``, then ``best_fit_max_distance_mm``), ``best_fit_iterations``
    a pass, its last pass Huber-weighted beyond ``alignment_huber_sigmas`` robust sigmas, the share of the points a
    fit must leave on the CAD (``alignment_min_inlier_share``) and the regions it fits on (``datum_regions``, by
    name among ``regions``); the reference spheres (``reference_spheres``, ``reference_sphere_diameter_mm``,
    searched within ``reference_sphere_search_mm`` of where the best fit expects them)."""

    alignment: str
    alignment_distances_mm: tuple[float, ...]
    alignment_huber_sigmas: float
    alignment_min_inlier_share: float
    best_fit_iterations: int
    best_fit_max_distance_mm: float
    datum_regions: tuple[str, ...]
    regions: tuple[RegionConfig, ...]
    reference_spheres: tuple[ReferenceSphereConfig, ...]
    reference_sphere_diameter_mm: float
    reference_sphere_search_mm: float


@dataclass(frozen=True)
class StationFit:
    """``T_F_W`` from the measurement AGV's planned stations (F) and where the job measured it (W).

    ``residuals_mm`` are the distances between each planned station origin and its measured one mapped
    into F by the fit (the chassis' drift off its plan, centimetres)."""

    T_F_W: np.ndarray
    residuals_mm: tuple[float, ...]

    @property
    def residual_mm(self) -> float:
        """RMS of the station residuals, mm."""
        return float(np.sqrt(np.mean(np.square(self.residuals_mm))))


@dataclass(frozen=True)
class SphereResidual:
    """One reference sphere: its CAD centre (F), the fitted centre (W) and, after the RPS fit, the
    distance between the CAD centre and the fitted one mapped into F (mm)."""

    name: str
    centre_F_mm: tuple[float, float, float]
    centre_W_mm: tuple[float, float, float]
    radius_mm: float  # free radius of the fit
    points: int
    residual_mm: float


@dataclass(frozen=True)
class RivalPose:
    """The best fit of the cloud in another pose than the chosen one (turned more than :data:`TWIN_DEG` from it: an
    unknown start's fit turned over, or another candidate) and what tells them apart (docs/inspection-method.md,
    "Alignment": twin poses). ``T_F_W`` places the cloud there, turned by ``turn_deg`` about the axis along ``axis``
    near ``centre_F_mm`` (the cloud's centroid, frame F) from the chosen pose. The evidence is the points whose
    residual (truncated at the last trim) differs by more than :data:`DISTINGUISH_SIGMAS` robust sigmas between
    the two poses: ``points_for`` lie closer to the CAD in the chosen pose, ``points_against`` in this one."""

    T_F_W: np.ndarray = field(repr=False)
    turn_deg: float
    axis: tuple[float, float, float]
    centre_F_mm: tuple[float, float, float]
    points_for: int
    points_against: int

    @property
    def z(self) -> float:
        """The sign test's statistic of the evidence: how many standard deviations of a fair coin's count the points
        for the chosen pose outnumber those against it by (0 without any)."""
        n = self.points_for + self.points_against
        return (self.points_for - self.points_against) / float(np.sqrt(n)) if n else 0.0

    @property
    def settled(self) -> bool:
        """Whether the chosen pose is proven over this one: the sign test beyond :data:`SETTLED_Z` (at least
        ``SETTLED_Z ** 2`` points that fit it and not this one, where none fits this one and not it)."""
        return self.z >= SETTLED_Z

    @property
    def unsettles_verdict(self) -> bool:
        """Not settled, and some point's deviation differs between the two poses: which verdict holds is unknown.
        A rival no point tells apart (an exactly symmetric part) gives the same deviations, shown at the mirror's
        places."""
        return not self.settled and self.points_for + self.points_against > 0

    def words(self) -> str:
        """The rival pose in words, with the evidence, for the report and the log."""
        a, c = self.axis, self.centre_F_mm
        return (f"the pose turned {self.turn_deg:.0f} deg about the axis along ({a[0]:+.3f}, {a[1]:+.3f}, "
                f"{a[2]:+.3f}) near ({c[0]:.0f}, {c[1]:.0f}, {c[2]:.0f}) mm fits as well (a symmetric part: "
                f"{self.points_for} points fit the chosen pose and not it, {self.points_against} it and not the "
                f"chosen one, z = {self.z:.1f} < {SETTLED_Z:g}): the deviations may be shown at their mirror's places"
                + ("" if self.points_for + self.points_against == 0 else " and differ between the two poses")
                + "; start the cloud within 30 deg of its place or align it by reference spheres")

    def summary(self) -> dict:
        """JSON-ready (report.json ``inspection.alignment.rival_pose``)."""
        return {"T_F_W": self.T_F_W.tolist(), "turn_deg": self.turn_deg, "axis": list(self.axis),
                "centre_F_mm": list(self.centre_F_mm), "points_for": self.points_for,
                "points_against": self.points_against, "z": round(self.z, 2), "settled": self.settled}


@dataclass(frozen=True)
class Alignment:
    """How the cloud was placed in the CAD frame: the method, ``T_F_W``, its residual and the details.

    ``residual_mm`` is the robust RMS point-to-plane residual of the best fit's last pass, the RMS of the
    sphere residuals for RPS, and 0 for none. ``spheres`` are the reference spheres fitted (RPS);
    ``excluded`` is a bool mask of the cloud's points on them, which the inspection leaves out.

    Best fit: ``free_directions`` names the motions the measured surface does not fix (the axis of a cylinder,
    an extrusion's length), held where the prior (the job's placement, or the given start) puts them.
    ``covariance`` is the fitted pose's 6x6 covariance, translation (mm) then rotation (rad), of a small
    motion in F about ``covariance_centre_F_mm`` (the inspected points' centroid, frame F) applied after
    ``T_F_W``: the true pose is about ``(p -> p + r x (p - c) + t) T_F_W`` with ``(t, r) ~ N(0, covariance)``.
    It is the residual scale squared times the inverse normal matrix of the fit's points (at most
    ``FINE_POINTS``, so conservative for a denser cloud), zero along the free directions (a motion along
    them moves no point off the surface). None for RPS and none. ``rival``: the best fit in another pose and
    the evidence between them (:class:`RivalPose`); None where no other pose was found."""

    method: str  # "best-fit", "rps" or "none"
    T_F_W: np.ndarray
    residual_mm: float
    start: str  # where the fit started from
    used_points: int = 0
    iterations: int = 0
    converged: bool = True
    spheres: tuple[SphereResidual, ...] = ()
    missing_spheres: tuple[str, ...] = ()  # "name: why"
    excluded: np.ndarray | None = field(default=None, repr=False)
    inlier_share: float = 1.0  # best fit: share of its points within best_fit_max_distance_mm of CAD at the end
    free_directions: tuple[str, ...] = ()  # best fit: what the measured surface does not fix, held by the prior
    covariance: np.ndarray | None = field(default=None, repr=False)  # best fit: 6x6, see below
    covariance_centre_F_mm: tuple[float, float, float] | None = None
    rival: RivalPose | None = None  # best fit: the best other pose found and what tells the two apart

    @property
    def ambiguity(self) -> str:
        """Where a rival pose is not ruled out (:attr:`RivalPose.settled`): it in words; else ""."""
        return "" if self.rival is None or self.rival.settled else self.rival.words()

    def summary(self) -> dict:
        """JSON-ready: method, residual_mm, start, T_F_W, translation and rotation of ``T_F_W`` and the
        per-sphere residuals (report.json ``inspection.alignment``)."""
        out = {
            "method": self.method,
            "residual_mm": self.residual_mm if np.isfinite(self.residual_mm) else None,
            "start": self.start,
            "T_F_W": self.T_F_W.tolist(),
            "translation_mm": float(np.linalg.norm(self.T_F_W[:3, 3])),
            "rotation_deg": float(np.degrees(F.rotation_angle(self.T_F_W))),
        }
        if self.method == "best-fit":
            out |= {"used_points": self.used_points, "iterations": self.iterations, "converged": self.converged,
                    "inlier_share": self.inlier_share, "free_directions": list(self.free_directions),
                    "ambiguity": self.ambiguity or None,
                    "rival_pose": None if self.rival is None else self.rival.summary()}
        if self.covariance is not None:
            out |= {"covariance": self.covariance.tolist(), "covariance_centre_F_mm": self.covariance_centre_F_mm,
                    "covariance_units": "t mm then r rad, a motion about covariance_centre_F_mm after T_F_W"}
        out |= {"spheres": [{"name": s.name, "centre_F_mm": list(s.centre_F_mm),
                             "centre_W_mm": list(s.centre_W_mm), "radius_mm": s.radius_mm,
                             "points": s.points, "residual_mm": s.residual_mm} for s in self.spheres],
                "missing_spheres": list(self.missing_spheres)}  # RPS: the fit's; best fit: how far it leaves them
        return out


def fit_rigid(src_mm: np.ndarray, dst_mm: np.ndarray) -> np.ndarray:
    """Least-squares rigid transform ``T_dst_src`` mapping the (N, 3) points ``src_mm`` onto ``dst_mm``
    (Kabsch; N >= 3 not all on a line)."""
    src, dst = np.asarray(src_mm, float), np.asarray(dst_mm, float)
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    U, _, Vt = np.linalg.svd((src - cs).T @ (dst - cd))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return F.make_transform(R, cd - R @ cs)


def _pose_points(T: np.ndarray) -> np.ndarray:
    """A pose as three points: its origin and ``STATION_ARM_MM`` along its x and its y axis (mm)."""
    return F.transform_points(T, np.array([[0.0, 0.0, 0.0], [STATION_ARM_MM, 0.0, 0.0], [0.0, STATION_ARM_MM, 0.0]]))


def align_stations(planned_T_F_V2: Sequence[np.ndarray], measured_T_W_V2: Sequence[np.ndarray]) -> StationFit:
    """``T_F_W`` by least squares from the measurement AGV's planned stations (F) and the poses the job
    measured there (W), each pose taken as three points (:data:`STATION_ARM_MM`), so one station gives
    the exact ``T_F_V2 inv(T_W_V2)`` and more average the chassis' drift off the plan."""
    if len(planned_T_F_V2) != len(measured_T_W_V2) or not planned_T_F_V2:
        raise InspectionError(
            f"station alignment needs matching stations, got {len(planned_T_F_V2)} planned and "
            f"{len(measured_T_W_V2)} measured"
        )
    src = np.vstack([_pose_points(T) for T in measured_T_W_V2])
    dst = np.vstack([_pose_points(T) for T in planned_T_F_V2])
    T_F_W = fit_rigid(src, dst)
    origins = F.transform_points(T_F_W, src[::3]) - dst[::3]
    return StationFit(T_F_W, tuple(float(v) for v in np.linalg.norm(origins, axis=1)))


def planned_stations(plan: Plan) -> list[np.ndarray | None]:
    """Per scan step of ``plan``, in order: the measurement AGV's planned station ``T_F_V2`` (mm) it is
    taken from, the pose of the last ``move_measure`` before it (None before any)."""
    out, station = [], None
    for step in plan.steps:
        if isinstance(step, MoveMeasure):
            station = F.planar_pose(step.x_mm, step.y_mm, step.heading_rad)
        elif isinstance(step, Scan):
            out.append(station)
    return out


def align_plan_stations(plan: Plan, scan_T_W_V2: Sequence[np.ndarray]) -> StationFit:
    """:func:`align_stations` from a job's scans: ``scan_T_W_V2`` is where the measurement AGV stood in W
    at each scan of ``plan`` (Eq. 5 from the scan's target reading and joints), averaged per station."""
    stations = planned_stations(plan)
    if len(stations) != len(scan_T_W_V2):
        raise InspectionError(f"the plan has {len(stations)} scans, the job measured {len(scan_T_W_V2)}")
    groups: dict[int, tuple[np.ndarray, list[np.ndarray]]] = {}
    for T_F_V2, T_W_V2 in zip(stations, scan_T_W_V2, strict=True):
        if T_F_V2 is not None:
            groups.setdefault(id(T_F_V2), (T_F_V2, []))[1].append(np.asarray(T_W_V2, float))
    if not groups:
        raise InspectionError("no scan of the plan follows a planned measurement-AGV station")
    return align_stations([g[0] for g in groups.values()], [F.mean_pose(g[1]) for g in groups.values()])


def _datum_rows(points_mm: np.ndarray, T_F_W: np.ndarray, cfg: AlignmentCriteria) -> np.ndarray | slice:
    """Which of the points (W) lie inside the named datum regions where ``T_F_W`` places them (indices); all
    (a slice) without datums."""
    if not cfg.datum_regions:
        return slice(None)
    regions = {r.name: r for r in cfg.regions}
    unknown = [n for n in cfg.datum_regions if n not in regions]
    if unknown:
        raise InspectionError(f"datum regions {unknown} are not among the inspection regions {sorted(regions)}")
    q = F.transform_points(T_F_W, points_mm)
    inside = np.zeros(len(points_mm), bool)
    for name in cfg.datum_regions:
        inside |= region_mask(q, regions[name])
    if inside.sum() < 6:
        raise InspectionError(f"only {int(inside.sum())} points in the datum regions {list(cfg.datum_regions)}")
    return np.flatnonzero(inside)


def _residuals(surface: CadSurface, points_mm: np.ndarray, T_F_W: np.ndarray, seen: SeenFrom | None,
               every: int) -> np.ndarray:
    """Signed distances (mm) of every ``every``-th point placed by ``T_F_W``; infinite where ``seen`` puts the
    point on the back of a closed face (:class:`SeenFrom`)."""
    rows = slice(None, None, max(1, every))
    cp = surface.closest(F.transform_points(T_F_W, points_mm[rows]))
    r = cp.signed_mm
    if seen is not None:
        r[seen.rows(rows).behind(T_F_W, cp)] = np.inf
    return r


def _robust_sigma(surface: CadSurface, points_mm: np.ndarray, T_F_W: np.ndarray, trim_mm: float,
                  seen: SeenFrom | None = None) -> float:
    """1.4826 x the median absolute point-to-plane residual (mm) of at most 50 000 evenly chosen points,
    placed by ``T_F_W``, among those within ``trim_mm`` of the surface (and not behind it, ``seen``); nan when
    none is."""
    r = _residuals(surface, points_mm, T_F_W, seen, len(points_mm) // 50_000)
    r = r[np.abs(r) <= trim_mm]
    return 1.4826 * float(np.median(np.abs(r - np.median(r)))) if len(r) else float("nan")


class AlignmentFailed(InspectionError):
    """The cloud could not be placed on the CAD: from the start nor from the global stage did a fit bring
    ``cfg.alignment_min_inlier_share`` of its points within ``best_fit_max_distance_mm`` of the surface.
    ``attempt`` is the best fit that was found (the report shows it beside the reason)."""

    def __init__(self, reason: str, attempt: Alignment):
        super().__init__(reason)
        self.attempt = attempt


#: a direction of the fit (rotations as millimetres at the cloud's RMS radius) whose normal-matrix eigenvalue is
#: below this share of the largest is not fixed by the measured surface: it is named and held by the prior. A
#: tessellated cylinder's facets fix its turn at about 1e-5 with 20 mm facets on a 2.2 m radius, 5e-5 with 50 mm
#: ones; a 12 mm door-surround pad on a 4 x 4.6 m barrel panel fixes its axis at 1e-4 (tests)
FREE_RATIO = 1e-5


def _spectrum(fit: SurfaceFit) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eigenvalues and eigenvectors of the fit's normal matrix with rotations scaled to millimetres at the
    points' RMS radius about its centre (``fit.scale``), and which of them are free (:data:`FREE_RATIO`)."""
    Hs = fit.normal_matrix / np.outer(fit.scale, fit.scale)
    lam, V = np.linalg.eigh(0.5 * (Hs + Hs.T))
    return lam, V, lam < FREE_RATIO * max(float(lam[-1]), 1e-300)


def free_directions(fit: SurfaceFit) -> tuple[str, ...]:
    """The directions about ``fit.centre_mm`` the measured surface does not fix (:data:`FREE_RATIO`), in words:
    a translation along a unit vector, or a rotation about an axis (along a unit vector, through a point;
    frame F). A cylinder leaves two (along and about its axis), an extrusion one, a plane three."""
    _, V, free = _spectrum(fit)
    if not free.any():
        return ()
    basis = V[:, free] / fit.scale[:, None]  # (t mm, r rad)
    _, _, Wt = np.linalg.svd(basis[3:], full_matrices=True)
    basis = basis @ Wt.T[:, ::-1]  # the pure translations first, then rotations with the least translation
    words = []
    for t, r in zip(basis[:3].T, basis[3:].T, strict=True):
        if np.linalg.norm(r) * fit.scale[3] < 1e-6 * np.linalg.norm(t):
            u = t / np.linalg.norm(t)
            words.append(f"translation along ({u[0]:+.3f}, {u[1]:+.3f}, {u[2]:+.3f})")
            continue
        a = r / np.linalg.norm(r)
        through = fit.centre_mm + np.cross(r, t) / float(r @ r)
        words.append(f"rotation about the axis along ({a[0]:+.3f}, {a[1]:+.3f}, {a[2]:+.3f}) through "
                     f"({through[0]:.1f}, {through[1]:.1f}, {through[2]:.1f}) mm")
    return tuple(words)


def covariance(fit: SurfaceFit) -> np.ndarray:
    """The 6x6 covariance (t mm, r rad; about ``fit.centre_mm``, frame F) of the fitted pose: the residual
    scale squared times the inverse of the normal matrix on the directions the surface fixes, zero on the free
    ones (a motion along them moves no point off the surface, so no deviation; they are held by the prior)."""
    lam, V, free = _spectrum(fit)
    cov_scaled = (V[:, ~free] / lam[~free]) @ V[:, ~free].T * fit.sigma_mm**2
    return cov_scaled / np.outer(fit.scale, fit.scale)


def _fine_fit(surface: CadSurface, p: np.ndarray, start_T_F_W: np.ndarray, prior_T_F_W: np.ndarray,
              cfg: AlignmentCriteria, levels: str = "all", seen: SeenFrom | None = None) -> tuple[SurfaceFit, int]:
    """The coarse-to-fine passes of :func:`fit_to_surface` from ``start_T_F_W`` (``levels``: "all", "coarse"
    (trims beyond :data:`FINE_FROM_MM`), "near" (the last of those alone: a start with most points within it) or
    "fine"), the free directions held at ``prior_T_F_W``, no point
    paired on the back of a closed face (``seen``): its last pass and the iterations of all. A pass leaving
    less than ``cfg.alignment_min_inlier_share`` of the points within its trim ends the fit
    (:class:`InspectionError`): the start was poor."""
    T, its = np.array(start_T_F_W, dtype=np.float64), 0
    last = cfg.best_fit_max_distance_mm
    fit = None
    distances = [d for d in (*cfg.alignment_distances_mm, last)
                 if levels == "all" or (d > FINE_FROM_MM) == (levels in ("coarse", "near"))]
    distances = distances[-1:] if levels == "near" else distances
    for distance in distances:
        rows = _datum_rows(p, T, cfg)
        datum, datum_seen = p[rows], None if seen is None else seen.rows(rows)
        huber = None
        if distance == last:
            sigma = _robust_sigma(surface, datum, T, last, datum_seen)
            huber = max(cfg.alignment_huber_sigmas * sigma, 1e-4) if np.isfinite(sigma) else None
        fit = best_fit(surface, datum, distance, cfg.best_fit_iterations, STEP_TOLERANCE * distance, start=T,
                       huber_mm=huber, prior=prior_T_F_W, seen=datum_seen,
                       max_points=COARSE_POINTS if distance > FINE_FROM_MM else FINE_POINTS)
        T, its = fit.T_F_M, its + fit.iterations
        if distance != last and _share(fit) < cfg.alignment_min_inlier_share:  # a poor start: no use refining it
            raise InspectionError(f"best fit: only {100 * _share(fit):.1f} % of the points within {distance} mm of "
                                  "the CAD surface")
    assert fit is not None
    return fit, its


COARSE_POINTS = 5_000  # points of a coarse pass (trim beyond FINE_FROM_MM): enough to find the part
FINE_POINTS = 50_000  # points of the fine passes: what fixes the pose
FINE_FROM_MM = 20.0
STEP_TOLERANCE = 1e-4  # a pass has converged when a step moves no point by more than this share of its trim


def _global_starts(surface: CadSurface, p: np.ndarray, start_T_F_W: np.ndarray) -> list[np.ndarray]:
    """The global stage's candidate ``T_F_W``: FPFH features of the cloud (placed by the start) matched by
    RANSAC against points sampled evenly on the CAD surface (:func:`global_registration.fpfh_ransac`), one a
    seed of :data:`GLOBAL_SEEDS`."""
    cad = _surface_samples(surface, GLOBAL_POINTS)
    src = F.transform_points(start_T_F_W, p[:: max(1, len(p) // GLOBAL_POINTS)])
    return [fpfh_ransac(src, cad, FeatureMatching(voxel_fraction=GLOBAL_VOXEL_FRACTION, seed=seed)) @ start_T_F_W
            for seed in range(GLOBAL_SEEDS)]


def _surface_samples(surface: CadSurface, n: int) -> np.ndarray:
    """``n`` points (F, mm) spread over the CAD's triangles by their area, the same ones every time."""
    V, T = np.asarray(surface.mesh.vertices), np.asarray(surface.mesh.triangles)
    a, b, c = V[T[:, 0]], V[T[:, 1]], V[T[:, 2]]
    area = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    rng = np.random.default_rng(0)
    pick = rng.choice(len(T), n, p=area / area.sum())
    u = rng.uniform(size=(n, 2))
    u = np.where(u.sum(axis=1, keepdims=True) > 1.0, 1.0 - u, u)
    return a[pick] + u[:, :1] * (b[pick] - a[pick]) + u[:, 1:] * (c[pick] - a[pick])


def _turned_over(surface: CadSurface, T_F_W: np.ndarray) -> list[np.ndarray]:
    """``T_F_W`` turned by 180 deg about each principal axis of the CAD surface through its centroid (F, of
    :data:`GLOBAL_POINTS` points sampled on it by area): the turns that map a symmetric part onto itself, so where a
    near-symmetric part (an arch about its crown's normal, a plate upside down) fits in its symmetric pose."""
    q = _surface_samples(surface, GLOBAL_POINTS)
    c = q.mean(axis=0)
    _, _, axes = np.linalg.svd(q - c, full_matrices=False)
    out = []
    for a in axes:
        turn = F.from_rotvec(np.zeros(3), np.pi * a)
        turn[:3, 3] = c - turn[:3, :3] @ c
        out.append(turn @ T_F_W)
    return out


def _global_fit(surface: CadSurface, p: np.ndarray, start_T_F_W: np.ndarray, prior_T_F_W: np.ndarray,
                cfg: AlignmentCriteria, seen: SeenFrom | None) -> tuple[SurfaceFit, int]:
    """The fit from the global stage: the coarse passes from each of its feature matches (:func:`_global_starts`),
    the fine ones from the one with the lowest truncated cost after them (:func:`_coarse_best`); no point paired on
    the back of a closed face (``seen``)."""
    best, its = _coarse_best(surface, p, _global_starts(surface, p, start_T_F_W), prior_T_F_W, cfg, seen)
    fit, n = _fine_fit(surface, p, best, prior_T_F_W, cfg, "fine", seen)
    return fit, its + n


def _turned_fit(surface: CadSurface, p: np.ndarray, fitted_T_F_W: np.ndarray, prior_T_F_W: np.ndarray,
                cfg: AlignmentCriteria, seen: SeenFrom | None) -> tuple[SurfaceFit, int]:
    """The fit of the cloud (W, mm) placed by ``fitted_T_F_W`` turned over (:func:`_turned_over`): the last coarse
    pass from each turn that leaves ``cfg.alignment_min_inlier_share`` of the points within its trim (a turn that
    maps the part nearly onto itself does), the fine ones from the one with the lowest truncated cost after it
    (:func:`_coarse_best`) unless the points rule it out (:func:`_ruled_out` within :data:`FINE_FROM_MM`).
    :class:`InspectionError` where none is left: the part has no twin pose."""
    reach = min(d for d in cfg.alignment_distances_mm if d > FINE_FROM_MM)
    turned = [T for T in _turned_over(surface, fitted_T_F_W) if _share_within(surface, p, T, reach, seen)
              >= cfg.alignment_min_inlier_share]
    best, its = _coarse_best(surface, p, turned, prior_T_F_W, cfg, seen, "near")
    if _ruled_out(surface, p, fitted_T_F_W, best, FINE_FROM_MM, seen):
        raise InspectionError("turned over, the part lies off the CAD")
    fit, n = _fine_fit(surface, p, best, prior_T_F_W, cfg, "fine", seen)
    return fit, its + n


def _coarse_best(surface: CadSurface, p: np.ndarray, starts: list[np.ndarray], prior_T_F_W: np.ndarray,
                 cfg: AlignmentCriteria, seen: SeenFrom | None, levels: str = "coarse") -> tuple[np.ndarray, int]:
    """Of the coarse passes (:func:`_fine_fit` at ``levels``) from each of ``starts`` (``T_F_W``), the pose with the
    lowest truncated cost (:func:`_final_cost` at :data:`FINE_FROM_MM`) and the iterations of all;
    :class:`InspectionError` where none leaves enough of the points on the CAD."""
    best, best_cost, its, why = None, np.inf, 0, "no candidate"
    for T in starts:
        try:
            coarse, n = _fine_fit(surface, p, T, prior_T_F_W, cfg, levels, seen)
        except InspectionError as e:
            why = str(e)
            continue
        its += n
        cost = _final_cost(surface, p, coarse.T_F_M, FINE_FROM_MM, seen)
        if cost < best_cost:
            best, best_cost = coarse.T_F_M, cost
    if best is None:
        raise InspectionError(why)
    return best, its


def _ruled_out(surface: CadSurface, p: np.ndarray, T_F_W: np.ndarray, rival_T_F_W: np.ndarray, within_mm: float,
               seen: SeenFrom | None) -> bool:
    """Whether, of at most :data:`COARSE_POINTS` of the cloud's points, those within ``within_mm`` of the CAD placed
    by ``T_F_W`` and not by ``rival_T_F_W`` outnumber those the other way round beyond :data:`SETTLED_Z` (the sign
    test of :class:`RivalPose`, on distances the next passes, trimmed closer, cannot bring back): the rival needs no
    further fit."""
    every = len(p) // COARSE_POINTS
    near = np.abs(_residuals(surface, p, T_F_W, seen, every)) <= within_mm
    near_rival = np.abs(_residuals(surface, p, rival_T_F_W, seen, every)) <= within_mm
    n_for, n_against = int(np.sum(near & ~near_rival)), int(np.sum(near_rival & ~near))
    return n_for - n_against >= SETTLED_Z * np.sqrt(max(n_for + n_against, 1))


GLOBAL_POINTS = 30_000  # the CAD's sampled points and the cloud's, at most, of the global stage
GLOBAL_VOXEL_FRACTION = 0.02
GLOBAL_SEEDS = 3


def _share(fit: SurfaceFit) -> float:
    return fit.used_points / max(fit.sampled_points, 1)


def _share_within(surface: CadSurface, p: np.ndarray, T_F_W: np.ndarray, trim_mm: float, seen: SeenFrom | None
                  ) -> float:
    """The share of at most :data:`COARSE_POINTS` of the cloud's points placed by ``T_F_W`` within ``trim_mm`` of
    the CAD surface (not on the back of a closed face, ``seen``)."""
    return float(np.mean(np.abs(_residuals(surface, p, T_F_W, seen, len(p) // COARSE_POINTS)) <= trim_mm))


def _final_cost(surface: CadSurface, p: np.ndarray, T_F_W: np.ndarray, trim_mm: float,
                seen: SeenFrom | None = None) -> float:
    """Mean truncated squared distance (mm^2) of at most :data:`FINE_POINTS` of the cloud's points (the same
    ones for every pose) placed by ``T_F_W``, a point on the back of a closed face (``seen``) at the trim: what
    candidates of the alignment are compared by."""
    d = np.minimum(np.abs(_residuals(surface, p, T_F_W, seen, len(p) // FINE_POINTS)), trim_mm)
    return float(np.mean(d * d))


def fit_to_surface(surface: CadSurface, points_mm: np.ndarray, start_T_F_W: np.ndarray, cfg: AlignmentCriteria,
                   start: str, prior_T_F_W: np.ndarray | None = None, seen: SeenFrom | None = None) -> Alignment:
    """:func:`_fit_from` with no point paired on the back of a closed face (``seen``: where the points were seen
    from), where that leaves the cloud's directions consistent with its fit: a cloud whose normals do not face
    its scanner (unoriented, a share beyond :data:`BEHIND_SHARE` of its points on closed faces behind them at
    the fit) is fitted again without them, and the log says so. A failure whose cloud and CAD differ in size as
    files in different units do says so (:func:`units.scale_mismatch`)."""
    p = as_points(points_mm)
    try:
        return _fit_seen_or_not(surface, p, start_T_F_W, cfg, start, prior_T_F_W, seen)
    except AlignmentFailed as e:
        hint = scale_mismatch(extent_mm(p), extent_mm(np.asarray(surface.mesh.vertices)), *UNITS_SUSPECT)
        if not hint:
            raise
        raise AlignmentFailed(f"{e}; {hint}", e.attempt) from e


UNITS_SUSPECT = (4.0, 20.0)  # a cloud this many times larger or smaller than its CAD that fails to align: units?


def _fit_seen_or_not(surface: CadSurface, p: np.ndarray, start_T_F_W: np.ndarray, cfg: AlignmentCriteria,
                     start: str, prior_T_F_W: np.ndarray | None, seen: SeenFrom | None) -> Alignment:
    """:func:`fit_to_surface`'s fit with ``seen``, else (none, or the cloud's directions not its scanner's)
    without it. Where the fit with ``seen`` found nothing from the start (a part given turned right round), it is
    tried again from where the fit without lands (a thin wall's far side lies millimetres from its near one)."""
    if seen is None:
        return _fit_from(surface, p, start_T_F_W, cfg, start, prior_T_F_W, None)
    out = _seen_fit(surface, p, start_T_F_W, cfg, start, prior_T_F_W, seen)
    if out is not None:
        return out
    plain = _fit_from(surface, p, start_T_F_W, cfg, start, prior_T_F_W, None)
    again = _seen_fit(surface, p, plain.T_F_W, cfg, f"{start}, refitted from its fit without its normals",
                      prior_T_F_W, seen)
    if again is not None:
        return again
    log.warning("the cloud's normals do not face where it was seen from (more than %.0f %% of its points on closed "
                "CAD faces behind them, or no fit): aligned without them", 100 * BEHIND_SHARE)
    return plain


def _seen_fit(surface: CadSurface, p: np.ndarray, start_T_F_W: np.ndarray, cfg: AlignmentCriteria, start: str,
              prior_T_F_W: np.ndarray | None, seen: SeenFrom) -> Alignment | None:
    """:func:`_fit_from` with ``seen`` where it leaves at most :data:`BEHIND_SHARE` of the points near closed
    faces behind them; None where it fails or leaves more."""
    try:
        out = _fit_from(surface, p, start_T_F_W, cfg, start, prior_T_F_W, seen)
    except AlignmentFailed:
        return None
    return out if _behind_share(surface, p, out.T_F_W, seen, cfg.best_fit_max_distance_mm) <= BEHIND_SHARE else None


#: a fit leaving more of its points near closed CAD faces behind them: the cloud's directions are not its scanner's
BEHIND_SHARE = 0.1


def _behind_share(surface: CadSurface, p: np.ndarray, T_F_W: np.ndarray, seen: SeenFrom, trim_mm: float) -> float:
    """Of at most :data:`FINE_POINTS` of the points placed by ``T_F_W`` within ``trim_mm`` of a closed face, the
    share on its back (:meth:`SeenFrom.behind`); 0 where none is near a closed face."""
    rows = slice(None, None, max(1, len(p) // FINE_POINTS))
    cp = surface.closest(F.transform_points(T_F_W, p[rows]))
    near = (np.abs(cp.signed_mm) <= trim_mm) & (seen.outward[cp.triangle_ids] != 0)
    return float(seen.rows(rows).behind(T_F_W, cp)[near].sum() / max(int(near.sum()), 1))


def _fit_from(surface: CadSurface, p: np.ndarray, start_T_F_W: np.ndarray, cfg: AlignmentCriteria, start: str,
              prior_T_F_W: np.ndarray | None, seen: SeenFrom | None) -> Alignment:
    """Robust best fit of the cloud (frame W, mm) to the CAD surface: trimmed, damped point-to-plane passes
    (:func:`inspect.best_fit`) at ``cfg.alignment_distances_mm`` then ``best_fit_max_distance_mm``, the last
    one Huber-weighted beyond ``alignment_huber_sigmas`` robust sigmas of its residuals.

    The passes start from ``start_T_F_W`` and, where the fit from it leaves less than
    ``cfg.alignment_min_inlier_share`` of the points within the last distance (a poor start; from an unknown
    start, no ``prior_T_F_W``, less than :data:`UNSURE_SHARE`), from the global stage (:func:`_global_fit`) as
    well; the lower truncated cost over the same points wins (:func:`_final_cost`), the start's fit on a tie. From
    an unknown start the winner is also turned over (:func:`_turned_over`: a near-symmetric part fits most of its
    points in its symmetric pose) and fitted again. Of two fits in poses apart, the one the points that tell them
    apart favour wins (:func:`_rival`) and the other is kept as the alignment's ``rival``: where the evidence does not
    prove the winner, an ambiguity the report and the verdict state. The directions the surface does not fix are held at
    ``prior_T_F_W`` (the job's placement; default the start) and named (:func:`free_directions`). A point does not
    pair with the back of a closed face (``seen``, :class:`SeenFrom`; None: every pair counts).
    Raises :class:`AlignmentFailed` when no fit leaves that share of the points on the CAD."""
    T0 = np.array(start_T_F_W, dtype=np.float64)
    prior = T0 if prior_T_F_W is None else np.asarray(prior_T_F_W, float)
    last = cfg.best_fit_max_distance_mm
    fits: list[tuple[SurfaceFit, str]] = []
    why: list[str] = []
    its = 0
    try:
        fit, its = _fine_fit(surface, p, T0, prior, cfg, "all", seen)
        fits.append((fit, start))
    except InspectionError as e:  # too few points near the surface from the start
        why.append(f"from {start}: {e}")
    poor = not fits or _share(fits[0][0]) < cfg.alignment_min_inlier_share
    if poor or (prior_T_F_W is None and _share(fits[0][0]) < UNSURE_SHARE):  # the features as well
        try:
            fit, n = _global_fit(surface, p, T0, prior, cfg, seen)
            its += n
            fits.append((fit, f"{start}, then the global stage (FPFH + RANSAC against the CAD)"))
        except InspectionError as e:
            why.append(f"from the global stage: {e}")
    if not fits:
        raise AlignmentFailed("alignment to CAD failed: " + "; ".join(why),
                              Alignment("best-fit", T0, float("nan"), start, inlier_share=0.0))
    costs = [_final_cost(surface, p, f.T_F_M, last, seen) for f, _ in fits]
    best = len(fits) - 1 if costs[-1] < costs[0] * (1.0 - COST_TIE) else 0
    if prior_T_F_W is None:  # a fit nobody vouches for: is it the part's only pose?
        try:
            fit, n = _turned_fit(surface, p, fits[best][0].T_F_M, prior, cfg, seen)
            its += n
            fits.append((fit, f"{fits[best][1]}, turned over"))
            costs.append(_final_cost(surface, p, fit.T_F_M, last, seen))
        except InspectionError:  # turned over it lies nowhere near the CAD: no twin
            pass
    (fit, how), rival = _rival(surface, p, fits, costs, best, last, seen)
    if not fit.converged:
        log.warning("best-fit alignment did not converge in %d iterations", fit.iterations)
    free = free_directions(fit)
    if free:
        log.warning("the measured surface does not fix %s: held where %s puts it", "; ".join(free), start)
    if rival is not None and not rival.settled:
        log.warning("%s", rival.words())
    rows = _datum_rows(p, fit.T_F_M, cfg)
    sigma = _robust_sigma(surface, p[rows], fit.T_F_M, last, None if seen is None else seen.rows(rows))
    out = Alignment("best-fit", fit.T_F_M, sigma, how, fit.used_points, its, fit.converged, inlier_share=_share(fit),
                    free_directions=free, covariance=covariance(fit),
                    covariance_centre_F_mm=tuple(map(float, fit.centre_mm)), rival=rival)
    if _share(fit) < cfg.alignment_min_inlier_share:
        raise AlignmentFailed(
            f"alignment to CAD failed: after the best fit from {start} and the global stage only "
            f"{100 * _share(fit):.1f} % of the points lie within {last} mm of the CAD surface (at least "
            f"{100 * cfg.alignment_min_inlier_share:.0f} % needed)", out)
    return out


def _rival(surface: CadSurface, p: np.ndarray, fits: list[tuple[SurfaceFit, str]], costs: list[float], best: int,
           trim_mm: float, seen: SeenFrom | None) -> tuple[tuple[SurfaceFit, str], RivalPose | None]:
    """Of the candidate fits (``costs`` their truncated costs, ``best`` the one the costs choose) and the best other
    one in a pose more than :data:`TWIN_DEG` apart, the one the points that tell the two apart favour
    (:func:`_pose_evidence`; the costs' choice on a tie) and the other as its rival, with that evidence (proven
    or not, :attr:`RivalPose.settled`); None where every candidate is in the chosen pose."""
    apart = [k for k in np.argsort(costs) if _turn_deg(fits[k][0].T_F_M, fits[best][0].T_F_M) > TWIN_DEG]
    if not apart:
        return fits[best], None
    rival = _pose_evidence(surface, p, fits[best][0].T_F_M, fits[apart[0]][0].T_F_M, trim_mm, seen)
    if rival.z >= 0.0:
        return fits[best], rival
    return fits[apart[0]], _pose_evidence(surface, p, fits[apart[0]][0].T_F_M, fits[best][0].T_F_M, trim_mm, seen)


def _turn_deg(T_a: np.ndarray, T_b: np.ndarray) -> float:
    """The angle (deg) of the turn between two placements ``T_F_W``."""
    return float(np.degrees(F.rotation_angle(T_a @ F.invert(T_b))))


def _pose_evidence(surface: CadSurface, p: np.ndarray, T_F_W: np.ndarray, rival_T_F_W: np.ndarray, trim_mm: float,
                   seen: SeenFrom | None) -> RivalPose:
    """What tells the pose ``T_F_W`` from ``rival_T_F_W`` (the cloud ``p``, W, mm): of at most :data:`FINE_POINTS`
    points, those whose residual truncated at ``trim_mm`` (a point behind a closed face at the trim, ``seen``)
    is smaller by more than :data:`DISTINGUISH_SIGMAS` robust sigmas of the pose's fit in the one pose than in the
    other, counted for each (:class:`RivalPose`). The points where the CAD and its turned copy differ decide;
    everywhere else both poses leave the same residual, whatever the noise or the defects."""
    every = len(p) // FINE_POINTS
    r = np.minimum(np.abs(_residuals(surface, p, T_F_W, seen, every)), trim_mm)
    r_rival = np.minimum(np.abs(_residuals(surface, p, rival_T_F_W, seen, every)), trim_mm)
    inside = r[r < trim_mm]
    sigma = 1.4826 * float(np.median(np.abs(inside - np.median(inside)))) if len(inside) else trim_mm
    tell = DISTINGUISH_SIGMAS * max(sigma, SIGMA_FLOOR_MM)
    turn = rival_T_F_W @ F.invert(T_F_W)
    axis = F.to_rotvec(turn)[1]
    axis = axis / max(float(np.linalg.norm(axis)), 1e-12)
    centre = F.transform_points(T_F_W, p.mean(axis=0)[None])[0]
    return RivalPose(np.array(rival_T_F_W, float), float(np.degrees(F.rotation_angle(turn))),
                     tuple(map(float, axis)), tuple(map(float, centre)), int(np.sum(r_rival - r > tell)),
                     int(np.sum(r - r_rival > tell)))


TWIN_DEG = 1.0  # two fits turned further apart than this are different poses
#: a point tells two poses apart where its truncated residual differs between them by more than this many robust
#: sigmas of the residuals (noise and the pose's own uncertainty stay well below it)
DISTINGUISH_SIGMAS = 3.0
SIGMA_FLOOR_MM = 1e-3  # the robust sigma taken at least (a noise-free cloud)
#: a pose is proven over a rival where the points telling them apart favour it by this many standard deviations of a
#: fair coin's count (sign test, one-sided p = 0.0013): at least 9 points for it and none against
SETTLED_Z = 3.0
#: from an unknown start (no prior), a fit leaving less than this share of the points within the last trim tries the
#: feature matches as well: a 4 mm skin with stringers fitted 32 mm and 8 deg off leaves 73 % on the CAD
UNSURE_SHARE = 0.98
COST_TIE = 0.05  # the global stage's fit wins only with a truncated cost lower than the start's by this share


def seen_from(surface: CadSurface, toward_W: np.ndarray) -> SeenFrom:
    """:class:`SeenFrom` of the cloud's directions toward where it was seen from (W; normalised here, zero
    kept as unknown) and of which way each closed patch of the CAD faces (:func:`cad_orientation.wind` by the
    volume alone; open patches 0)."""
    d = np.asarray(toward_W, np.float64)
    length = np.linalg.norm(d, axis=1, keepdims=True)
    d = np.divide(d, length, out=np.zeros_like(d), where=length > 0)
    o = wind(np.asarray(surface.mesh.vertices), np.asarray(surface.mesh.triangles), patches=surface.patches)
    outward = np.where(o.reversed == surface.reversed, 1, -1) * o.closed
    return SeenFrom(d, outward.astype(np.int8))


def within(points_mm: np.ndarray, centre_mm, radius_mm: float) -> np.ndarray:
    """Indices (ascending) of the points no further than ``radius_mm`` from ``centre_mm`` (same frame, mm): a
    pass over the cloud, cheaper than a KD tree of millions of points asked about a few spheres."""
    c = np.asarray(centre_mm, float)
    pad = radius_mm + 1e-9 * (1.0 + np.abs(c))  # a box around the ball, wider by more than any rounding
    x = points_mm[:, 0]
    box = np.flatnonzero((x >= c[0] - pad[0]) & (x <= c[0] + pad[0]))
    box = box[np.all(np.abs(points_mm[box, 1:] - c[1:]) <= pad[1:], axis=1)]
    diff = points_mm[box] - c
    return box[np.einsum("ij,ij->i", diff, diff) <= radius_mm * radius_mm]


def locate_spheres(surface: CadSurface, points_mm: np.ndarray, start_T_F_W: np.ndarray, cfg: AlignmentCriteria,
                   noise_mm: float = 0.05) -> tuple[list[tuple[str, np.ndarray, np.ndarray, float, int]], list[str]]:
    """Fit each configured reference sphere in the cloud (W) among the points within
    ``reference_sphere_search_mm`` of where ``start_T_F_W`` (a best fit: to a fraction of a millimetre)
    expects its centre and off the CAD surface by more than :data:`OFF_SURFACE_MM` there (the sphere
    stands out of the part); ``noise_mm`` is the scanner's 1-sigma noise (the fit's inlier band). Returns
    the found ones as (name, CAD centre F, fitted centre W, free radius mm, points) and the missing ones as
    "name: why"."""
    r = 0.5 * cfg.reference_sphere_diameter_mm
    T_W_F = F.invert(start_T_F_W)
    found, missing = [], []
    for sphere in cfg.reference_spheres:
        centre_F = np.array(sphere.centre_mm, float)
        guess = F.transform_points(T_W_F, centre_F[None])[0]
        near = points_mm[within(points_mm, guess, cfg.reference_sphere_search_mm)]
        if len(near):
            near = near[np.abs(surface.signed_distance(F.transform_points(start_T_F_W, near))) > OFF_SURFACE_MM]
        try:
            fit = fit_sphere(near, r, noise_mm=noise_mm, fixed_radius=True)
            shell = points_mm[within(points_mm, fit.centre, r + 4.0 * noise_mm + 0.5)]
            shell = shell[np.abs(np.linalg.norm(shell - fit.centre, axis=1) - r) < 4.0 * noise_mm + 0.1]
            fit = fit_sphere(shell, r, noise_mm=noise_mm, fixed_radius=True)
        except PlateError as e:
            missing.append(f"{sphere.name}: {e}")
            continue
        if abs(fit.free_radius_mm - r) > max(0.3, 0.02 * r):
            missing.append(f"{sphere.name}: fitted radius {fit.free_radius_mm:.3f} mm, expected {r:.3f} mm")
            continue
        found.append((sphere.name, centre_F, fit.centre, fit.free_radius_mm, fit.n_inliers))
    return found, missing


def align_rps(surface: CadSurface, points_mm: np.ndarray, start_T_F_W: np.ndarray, cfg: AlignmentCriteria,
              start: str) -> Alignment:
    """``T_F_W`` from the reference spheres, searched for where ``start_T_F_W`` (a best fit) puts them:
    their fitted centres (W) onto their CAD centres (F) by least squares, twice (the second search where
    the first RPS fit puts them); at least three spheres."""
    p = as_points(points_mm)
    T = np.array(start_T_F_W, dtype=np.float64)
    for _ in range(2):
        found, missing = locate_spheres(surface, p, T, cfg)
        if len(found) < 3:
            raise InspectionError(f"RPS alignment needs 3 reference spheres, found {len(found)}: "
                                  + "; ".join(missing))
        T = fit_rigid(np.array([f[2] for f in found]), np.array([f[1] for f in found]))
    spheres = sphere_residuals(found, T)
    return Alignment("rps", T, float(np.sqrt(np.mean([s.residual_mm**2 for s in spheres]))), start, spheres=spheres,
                     missing_spheres=tuple(missing), excluded=sphere_points(p, spheres, cfg))


def sphere_residuals(found: list[tuple[str, np.ndarray, np.ndarray, float, int]], T_F_W: np.ndarray
                     ) -> tuple[SphereResidual, ...]:
    """The spheres of :func:`locate_spheres` with their residuals under ``T_F_W`` (mm)."""
    if not found:
        return ()
    res = np.linalg.norm(F.transform_points(T_F_W, np.array([f[2] for f in found])) - np.array([f[1] for f in found]),
                         axis=1)
    return tuple(SphereResidual(name, tuple(map(float, cF)), tuple(map(float, cW)), float(rad), int(n), float(e))
                 for (name, cF, cW, rad, n), e in zip(found, res, strict=True))


def sphere_balls(spheres: tuple[SphereResidual, ...], cfg: AlignmentCriteria) -> tuple[tuple[np.ndarray, float], ...]:
    """The balls (centre W mm, radius mm) of the fitted spheres and 3 mm beyond them (their bases): no part surface."""
    return tuple((np.asarray(s.centre_W_mm, float), 0.5 * cfg.reference_sphere_diameter_mm + 3.0) for s in spheres)


def in_balls(points_mm: np.ndarray, balls) -> np.ndarray:
    """(N,) bool: the points (N, 3) in any of ``balls`` ((centre (3,), radius) each; same frame, mm)."""
    inside = np.zeros(len(points_mm), bool)
    for centre, radius in balls:
        inside[within(points_mm, centre, radius)] = True
    return inside


def sphere_points(points_mm: np.ndarray, spheres: tuple[SphereResidual, ...], cfg: AlignmentCriteria) -> np.ndarray:
    """(N,) bool: the points in :func:`sphere_balls`."""
    return in_balls(points_mm, sphere_balls(spheres, cfg))


def align(surface: CadSurface, points_mm: np.ndarray, cfg: AlignmentCriteria, start_T_F_W: np.ndarray | None = None,
          start: str = "as given", prior_T_F_W: np.ndarray | None = None, toward_W: np.ndarray | None = None
          ) -> Alignment:
    """Place the cloud (frame W, mm) in the CAD frame F by ``cfg.alignment`` from ``start_T_F_W`` (default
    identity: the cloud is roughly in F already); ``prior_T_F_W`` is a placement known independently (the
    job's anchor), None where the start is unknown (:func:`fit_to_surface`); ``toward_W`` (N, 3): each point's
    direction toward where it was seen from (a scanner's normals, W), which keeps points off the back of the
    CAD's closed faces (:func:`seen_from`)."""
    T0 = np.eye(4) if start_T_F_W is None else np.asarray(start_T_F_W, float)
    if cfg.alignment == "none":
        return Alignment("none", T0, 0.0, start)
    seen = None if toward_W is None else seen_from(surface, toward_W)
    fit = fit_to_surface(surface, points_mm, T0, cfg, start, prior_T_F_W, seen)  # RPS: the pre-alignment
    if cfg.alignment == "rps":
        return align_rps(surface, points_mm, fit.T_F_W, cfg, f"{start}, then a best fit")
    if not cfg.reference_spheres:
        return fit
    found, _ = locate_spheres(surface, as_points(points_mm), fit.T_F_W, cfg)  # spheres where there are: not part
    spheres = sphere_residuals(found, fit.T_F_W)
    return replace(fit, spheres=spheres, excluded=sphere_points(as_points(points_mm), spheres, cfg))
