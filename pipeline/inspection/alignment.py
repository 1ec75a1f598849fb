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

import numpy as np
from tandemscan.config.models import InspectionConfig
from tandemscan.pipeline.calibration.plate import PlateError, fit_sphere
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.inspection.inspect import CadSurface, InspectionError, as_points, best_fit, region_mask
from tandemscan.pipeline.planning.plan import MoveMeasure, Plan, Scan

log = logging.getLogger(__name__)

OFF_SURFACE_MM = 1.0  # a point this far off the CAD surface near a sphere's place may lie on the sphere
STATION_ARM_MM = 1000.0  # a station pose enters the fit as its origin and points this far along its x and y


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
class Alignment:
    """How the cloud was placed in the CAD frame: the method, ``T_F_W``, its residual and the details.

    ``residual_mm`` is the robust RMS point-to-plane residual of the best fit's last pass, the RMS of the
    sphere residuals for RPS, and 0 for none. ``spheres`` are the reference spheres fitted (RPS);
    ``excluded`` is a bool mask of the cloud's points on them, which the inspection leaves out."""

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

    def summary(self) -> dict:
        """JSON-ready: method, residual_mm, start, T_F_W, translation and rotation of ``T_F_W`` and the
        per-sphere residuals (report.json ``inspection.alignment``)."""
        out = {
            "method": self.method,
            "residual_mm": self.residual_mm,
            "start": self.start,
            "T_F_W": self.T_F_W.tolist(),
            "translation_mm": float(np.linalg.norm(self.T_F_W[:3, 3])),
            "rotation_deg": float(np.degrees(F.rotation_angle(self.T_F_W))),
        }
        if self.method == "best-fit":
            out |= {"used_points": self.used_points, "iterations": self.iterations, "converged": self.converged}
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


def _datum_points(points_mm: np.ndarray, T_F_W: np.ndarray, cfg: InspectionConfig) -> np.ndarray:
    """The points (W) inside the named datum regions where ``T_F_W`` places them; all without datums."""
    if not cfg.datum_regions:
        return points_mm
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
    return points_mm[inside]


def _robust_sigma(surface: CadSurface, points_mm: np.ndarray, T_F_W: np.ndarray, trim_mm: float) -> float:
    """1.4826 x the median absolute point-to-plane residual (mm) of at most 50 000 evenly chosen points,
    placed by ``T_F_W``, among those within ``trim_mm`` of the surface; nan when none is."""
    r = surface.signed_distance(F.transform_points(T_F_W, points_mm[:: max(1, len(points_mm) // 50_000)]))
    r = r[np.abs(r) <= trim_mm]
    return 1.4826 * float(np.median(np.abs(r - np.median(r)))) if len(r) else float("nan")


def fit_to_surface(surface: CadSurface, points_mm: np.ndarray, start_T_F_W: np.ndarray, cfg: InspectionConfig,
                   start: str) -> Alignment:
    """Robust best fit of the cloud (frame W, mm) to the CAD surface from ``start_T_F_W``: trimmed
    point-to-plane passes at ``cfg.alignment_distances_mm`` then ``best_fit_max_distance_mm``, the last
    one Huber-weighted beyond ``alignment_huber_sigmas`` robust sigmas of its residuals. The alignment's
    residual is that robust sigma after the fit."""
    p = as_points(points_mm)
    T = np.array(start_T_F_W, dtype=np.float64)
    its, converged, used = 0, True, 0
    last = cfg.best_fit_max_distance_mm
    for distance in (*cfg.alignment_distances_mm, last):
        datum = _datum_points(p, T, cfg)
        huber = None
        if distance == last:
            sigma = _robust_sigma(surface, datum, T, last)
            huber = max(cfg.alignment_huber_sigmas * sigma, 1e-4) if np.isfinite(sigma) else None
        T, its, converged, used = best_fit(surface, datum, distance, cfg.best_fit_iterations, start=T, huber_mm=huber)
    if not converged:
        log.warning("best-fit alignment did not converge in %d iterations", its)
    return Alignment("best-fit", T, _robust_sigma(surface, _datum_points(p, T, cfg), T, last), start, used, its,
                     converged)


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


def locate_spheres(surface: CadSurface, points_mm: np.ndarray, start_T_F_W: np.ndarray, cfg: InspectionConfig,
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


def align_rps(surface: CadSurface, points_mm: np.ndarray, start_T_F_W: np.ndarray, cfg: InspectionConfig,
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


def sphere_points(points_mm: np.ndarray, spheres: tuple[SphereResidual, ...], cfg: InspectionConfig) -> np.ndarray:
    """(N,) bool: the points on the fitted spheres or within 3 mm of them (their bases): no part surface."""
    excluded = np.zeros(len(points_mm), bool)
    for s in spheres:
        excluded[within(points_mm, s.centre_W_mm, 0.5 * cfg.reference_sphere_diameter_mm + 3.0)] = True
    return excluded


def align(surface: CadSurface, points_mm: np.ndarray, cfg: InspectionConfig, start_T_F_W: np.ndarray | None = None,
          start: str = "as given") -> Alignment:
    """Place the cloud (frame W, mm) in the CAD frame F by ``cfg.alignment`` from ``start_T_F_W`` (default
    identity: the cloud is roughly in F already)."""
    T0 = np.eye(4) if start_T_F_W is None else np.asarray(start_T_F_W, float)
    if cfg.alignment == "none":
        return Alignment("none", T0, 0.0, start)
    fit = fit_to_surface(surface, points_mm, T0, cfg, start)  # for RPS the pre-alignment that finds the spheres
    if cfg.alignment == "rps":
        return align_rps(surface, points_mm, fit.T_F_W, cfg, f"{start}, then a best fit")
    if not cfg.reference_spheres:
        return fit
    found, _ = locate_spheres(surface, as_points(points_mm), fit.T_F_W, cfg)  # spheres where there are: not part
    spheres = sphere_residuals(found, fit.T_F_W)
    return replace(fit, spheres=spheres, excluded=sphere_points(as_points(points_mm), spheres, cfg))
