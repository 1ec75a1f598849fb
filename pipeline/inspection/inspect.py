"""Deviation of a measured cloud from its CAD mesh: signed distances, statistics, tolerances, best fit.

Frames and units: the cloud and the mesh are both in the part/CAD frame F, millimetres. A deviation is the
signed distance from a point to the closest point of the CAD surface, positive on the side the surface's
outward normal points to (material above the design), negative below it.

Open3D's ``RaycastingScene`` works in float32. The mesh is therefore shifted to its bounding-box centre
before it is handed over and every query is shifted the same way, which keeps the rounding error of a
3 m part at about 0.1 um; distances and signs are then formed in float64.
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import open3d as o3d
from tandemscan.config.models import InspectionConfig, RegionConfig
from tandemscan.pipeline.geometry.frames import from_rotvec, rotation_angle, transform_points
from tandemscan.pipeline.geometry.part import enclosed_volume_mm3, triangles_closed
from tandemscan.pipeline.inspection.deviation_areas import DeviationArea, find_deviation_areas

if TYPE_CHECKING:
    from tandemscan.pipeline.inspection.verdict import Judgement

log = logging.getLogger(__name__)


class InspectionError(ValueError):
    """Bad input to the inspection: an empty cloud, a mesh without triangles, non-finite points."""


def as_points(points: np.ndarray, what: str = "cloud") -> np.ndarray:
    """``points`` as a finite float64 (N, 3) array with N >= 1, or :class:`InspectionError`."""
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InspectionError(f"{what}: expected an (N, 3) array of points, got shape {arr.shape}")
    if len(arr) == 0:
        raise InspectionError(f"{what}: no points")
    if not np.isfinite(arr).all():
        raise InspectionError(f"{what}: {int((~np.isfinite(arr)).any(axis=1).sum())} points are not finite")
    return arr


@dataclass(frozen=True)
class ClosestPoints:
    """Closest CAD surface points to a set of queries (frame F, mm)."""

    points_mm: np.ndarray  # (N, 3) closest point on the surface
    normals: np.ndarray  # (N, 3) outward unit normal of the triangle holding it
    triangle_ids: np.ndarray  # (N,) index into the mesh's triangles
    signed_mm: np.ndarray  # (N,) signed distance, + along the outward normal


CLOSEST_CHUNK = 262_144  # query points a chunk of :meth:`CadSurface.closest` (and of the other chunked passes)


def in_chunks(fn, T: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``fn(T, rows)`` (``frames.transform_points`` or ``rotate_vectors``: row by row) a chunk of
    :data:`CLOSEST_CHUNK` rows at a time: the same numbers, with the temporaries of a whole cloud's pass
    kept in the cache (8 M points: 0.3 s CPU instead of 1.4 s)."""
    rows = np.asarray(rows, float)
    out = np.empty_like(rows)
    for lo in range(0, len(rows), CLOSEST_CHUNK):
        out[lo:lo + CLOSEST_CHUNK] = fn(T, rows[lo:lo + CLOSEST_CHUNK])
    return out


class CadSurface:
    """The CAD mesh as a distance field: closest points and signed distances of queries, frame F, mm."""

    def __init__(self, mesh: o3d.geometry.TriangleMesh):
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        triangles = np.asarray(mesh.triangles, dtype=np.int64)
        if len(triangles) == 0 or len(vertices) < 3:
            raise InspectionError("CAD mesh has no triangles")
        if not np.isfinite(vertices).all():
            raise InspectionError("CAD mesh has non-finite vertices")
        self.mesh = mesh
        self.origin_mm = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
        local = (vertices - self.origin_mm).astype(np.float32)
        self.flipped = triangles_closed(triangles) and enclosed_volume_mm3(local, triangles) < 0.0
        if self.flipped:  # a closed mesh wound inside out: its normals would point into the material
            log.warning("CAD mesh is wound inside out (negative volume); using its triangles reversed")
            triangles = triangles[:, ::-1].copy()
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.core.Tensor(local), o3d.core.Tensor(triangles.astype(np.uint32)))

    @property
    def scene(self) -> o3d.t.geometry.RaycastingScene:
        """The Open3D scene; its coordinates are frame F shifted by ``-origin_mm``."""
        return self._scene

    def closest(self, points_mm: np.ndarray) -> ClosestPoints:
        """Closest surface point, outward normal and signed distance of every query point. Asked in chunks of
        :data:`CLOSEST_CHUNK` points, so the float64 work on each stays in the cache (the same numbers)."""
        p = as_points(points_mm)
        n = len(p)
        out = ClosestPoints(np.empty((n, 3)), np.empty((n, 3)), np.empty(n, np.int64), np.empty(n))
        for lo in range(0, n, CLOSEST_CHUNK):
            self._closest_into(p[lo:lo + CLOSEST_CHUNK], out, slice(lo, lo + CLOSEST_CHUNK))
        return out

    def _closest_into(self, points_mm: np.ndarray, out: ClosestPoints, at: slice) -> None:
        p = points_mm - self.origin_mm
        ans = self._scene.compute_closest_points(o3d.core.Tensor.from_numpy(p.astype(np.float32)))
        closest = out.points_mm[at]
        closest[:] = ans["points"].numpy()
        normals = out.normals[at]
        normals[:] = ans["primitive_normals"].numpy()
        normals /= np.sqrt(np.einsum("ij,ij->i", normals, normals))[:, None]
        p -= closest  # p - closest from here on
        signed = out.signed_mm[at]
        np.sqrt(np.einsum("ij,ij->i", p, p), out=signed)
        signed[np.einsum("ij,ij->i", p, normals) < 0.0] *= -1.0
        closest += self.origin_mm
        out.triangle_ids[at] = ans["primitive_ids"].numpy()

    def group_masks(self, triangle_ids: np.ndarray) -> list[tuple[str, np.ndarray]]:
        """(name, bool mask) per material group of the mesh, for points whose closest triangles are given;
        empty when the mesh has fewer than two groups. Names are ``mesh group <material id>``."""
        groups = np.asarray(self.mesh.triangle_material_ids)
        if len(groups) != len(self.mesh.triangles) or len(np.unique(groups)) < 2:
            return []
        of_point = groups[triangle_ids]
        return [(f"mesh group {g}", of_point == g) for g in np.unique(groups)]

    def signed_distance(self, points_mm: np.ndarray) -> np.ndarray:
        """(N,) signed distance of every point to the surface, mm (+ outside along the outward normal)."""
        return self.closest(points_mm).signed_mm


@dataclass(frozen=True)
class DeviationStats:
    """Summary of a set of signed deviations, mm. ``sigma_mm`` is the sample standard deviation."""

    count: int
    mean_mm: float
    sigma_mm: float
    rms_mm: float
    min_mm: float
    max_mm: float
    p5_mm: float
    p95_mm: float

    @classmethod
    def of(cls, deviations_mm: np.ndarray) -> DeviationStats | None:
        """Statistics of ``deviations_mm``; None when it is empty."""
        d = np.asarray(deviations_mm, dtype=np.float64)
        if d.size == 0:
            return None
        p5, p95 = np.percentile(d, [5.0, 95.0])
        return cls(
            count=int(d.size),
            mean_mm=float(d.mean()),
            sigma_mm=float(d.std(ddof=1)) if d.size > 1 else 0.0,
            rms_mm=float(np.sqrt(np.mean(d * d))),
            min_mm=float(d.min()),
            max_mm=float(d.max()),
            p5_mm=float(p5),
            p95_mm=float(p95),
        )


@dataclass(frozen=True)
class ToleranceResult:
    """Share of points inside ``[lower_mm, upper_mm]`` (inclusive), above it and below it, in percent."""

    lower_mm: float
    upper_mm: float
    in_pct: float
    above_pct: float
    below_pct: float

    @classmethod
    def of(cls, deviations_mm: np.ndarray, lower_mm: float, upper_mm: float) -> ToleranceResult | None:
        """Tolerance shares of ``deviations_mm``; None when it is empty."""
        if lower_mm > upper_mm:
            raise InspectionError(f"tolerance lower {lower_mm} mm is above upper {upper_mm} mm")
        d = np.asarray(deviations_mm, dtype=np.float64)
        if d.size == 0:
            return None
        above = float(np.count_nonzero(d > upper_mm)) * 100.0 / d.size
        below = float(np.count_nonzero(d < lower_mm)) * 100.0 / d.size
        return cls(lower_mm, upper_mm, 100.0 - above - below, above, below)


@dataclass(frozen=True)
class RegionResult:
    """Deviation statistics and tolerance shares of the points inside one named region."""

    name: str
    stats: DeviationStats | None
    tolerance: ToleranceResult | None


@dataclass(frozen=True)
class BestFit:
    """Best-fit alignment of the cloud to CAD, reported apart from the as-measured deviation.

    ``T_F_M`` maps the measured cloud (as delivered, frame M = nominal F) onto the CAD frame F.
    """

    T_F_M: np.ndarray
    translation_mm: float
    rotation_deg: float
    iterations: int
    converged: bool
    used_points: int
    deviations_mm: np.ndarray = field(repr=False)
    stats: DeviationStats | None = None
    tolerance: ToleranceResult | None = None


@dataclass(frozen=True)
class InspectionResult:
    """Everything the report shows about one cloud against its CAD mesh (frame F, mm)."""

    points_mm: np.ndarray = field(repr=False)
    deviations_mm: np.ndarray = field(repr=False)
    cad_normals: np.ndarray = field(repr=False)  # (N, 3) outward normal of the closest CAD triangle
    stats: DeviationStats
    tolerance: ToleranceResult
    regions: tuple[RegionResult, ...]
    best_fit: BestFit | None
    best_fit_note: str = ""  # why there is no best fit when one was asked for
    areas: tuple[DeviationArea, ...] = ()  # beyond the band, largest |extreme| first
    triangle_ids: np.ndarray | None = field(default=None, repr=False)  # (N,) closest CAD triangle per point
    judgement: Judgement | None = field(default=None, repr=False)  # the decision rule's (``verdict.judge``)

    @property
    def verdict(self) -> str:
        """The judgement's "pass", "fail" or "indeterminate"; without one, by simple acceptance: "pass" when no
        area of the surface lies beyond the tolerance band, else "fail"."""
        if self.judgement is not None:
            return self.judgement.verdict
        return "fail" if self.areas else "pass"


def region_mask(points_mm: np.ndarray, region: RegionConfig) -> np.ndarray:
    """(N,) bool: points inside the region's box (bounds inclusive), frame F."""
    lo, hi = np.asarray(region.min_mm), np.asarray(region.max_mm)
    return np.all((points_mm >= lo) & (points_mm <= hi), axis=1)


def best_fit(
    surface: CadSurface,
    points_mm: np.ndarray,
    max_distance_mm: float,
    iterations: int = 30,
    tolerance_mm: float = 1e-7,
    max_points: int = 50_000,
    *,
    start: np.ndarray | None = None,
    huber_mm: float | None = None,
) -> tuple[np.ndarray, int, bool, int]:
    """Point-to-plane ICP of ``points_mm`` onto the CAD surface itself (no sampling of the mesh).

    The points are in a frame M placed in F by ``start`` (``T_F_M``, default identity). Each iteration
    pairs every point with its closest surface point and keeps the pairs closer than ``max_distance_mm``
    (a trimmed fit), so outliers and real form errors beyond it do not pull the fit; with ``huber_mm`` the
    residuals beyond it are weighted down as Huber's (weight ``huber_mm / |r|``), so a dent or a bulge
    within the trim pulls little either. Returns ``(T_F_M, iterations run, converged, pairs used in the
    last iteration)``; converged means the last update moved no point of the cloud's extent by more than
    ``tolerance_mm``, or stopped lowering the (weighted) RMS residual (a shape with a symmetry leaves the
    fit free along it). At most ``max_points`` points, an even subsample, take part.
    """
    p = np.asarray(points_mm)
    p = as_points(p[:: max(1, int(np.ceil(len(p) / max_points)))])  # the points that take part
    T = np.eye(4) if start is None else np.array(start, dtype=np.float64)
    used = 0
    rms_before = np.inf
    for it in range(1, iterations + 1):
        q = transform_points(T, p)
        centre = q.mean(axis=0)
        extent = max(float(np.linalg.norm(q - centre, axis=1).max()), 1.0)
        cp = surface.closest(q)
        keep = np.abs(cp.signed_mm) <= max_distance_mm
        used = int(keep.sum())
        if used < 6:
            raise InspectionError(
                f"best fit: only {used} points within {max_distance_mm} mm of the CAD surface"
            )
        qc, n = q[keep] - centre, cp.normals[keep]
        r = cp.signed_mm[keep]
        w = np.ones_like(r) if huber_mm is None else np.minimum(1.0, huber_mm / np.maximum(np.abs(r), 1e-12))
        rms = float(np.sqrt(np.sum(w * r * r) / np.sum(w)))
        if rms_before - rms < 1e-3 * tolerance_mm:
            return T, it, True, used
        rms_before = rms
        sw = np.sqrt(w)[:, None]
        A = np.hstack([np.cross(qc, n), n])  # d(residual)/d(omega, t) for small rotations about `centre`
        x, *_ = np.linalg.lstsq(A * sw, -r * sw[:, 0], rcond=None)
        omega, t = x[:3], x[3:]
        step = from_rotvec(t, omega)
        step[:3, 3] += centre - step[:3, :3] @ centre
        T = step @ T
        if float(np.linalg.norm(omega)) * extent + float(np.linalg.norm(t)) < tolerance_mm:
            return T, it, True, used
    return T, iterations, False, used


SMALL_MOVE_MM = 0.005  # a best fit moving no point further than this updates the deviations to first order


def signed_distance_moved(surface: CadSurface, points_mm: np.ndarray, T: np.ndarray, before: ClosestPoints
                          ) -> np.ndarray:
    """(N,) signed distances (mm) of ``points_mm`` (frame F) moved by ``T``, given ``before``, their
    :meth:`CadSurface.closest` where they are. Where ``T`` moves no point by more than :data:`SMALL_MOVE_MM`
    (a best fit after an alignment: microns) it is the first-order update ``d + grad(d) . delta`` (the
    gradient is the closest triangle's normal, the unit vector from the closest point where that is an
    edge or a corner more than 1 um away):
    exact to second order, ``|delta|^2 / d`` (below 1 nm at 0.04 mm off the surface), and at most
    ``2 |delta|`` off on the few points where the closest triangle changes at a concave crease. Larger moves
    are queried anew."""
    p = as_points(points_mm)
    if not len(p) or _moves_further(T, p, SMALL_MOVE_MM):
        return surface.signed_distance(transform_points(T, p))
    out = np.empty(len(p))
    for lo in range(0, len(p), CLOSEST_CHUNK):  # a chunk at a time: its float64 work stays in the cache
        at = slice(lo, lo + CLOSEST_CHUNK)
        q, d = p[at], before.signed_mm[at]
        delta = transform_points(T, q) - q
        grad = before.normals[at].copy()  # on a triangle's face (nearly every point): its normal, exactly
        off = np.abs(d) > 1e-3
        to_point = (q[off] - before.points_mm[at][off]) / d[off, None]
        edge = np.einsum("ij,ij->i", to_point, grad[off]) < 0.9999  # closest on an edge or a corner
        grad[np.flatnonzero(off)[edge]] = to_point[edge]
        out[at] = d + np.einsum("ij,ij->i", grad, delta)
    return out


def _moves_further(T: np.ndarray, points_mm: np.ndarray, limit_mm: float) -> bool:
    """Whether ``T`` moves some point of ``points_mm`` further than ``limit_mm`` (mm). A rigid motion's
    displacement is affine in the point, so its length is largest at a corner of the points' bounding box:
    where no corner moves further no point does; else the points are measured, a chunk at a time."""
    lo, hi = points_mm.min(axis=0), points_mm.max(axis=0)
    corners = np.array([[hi[i] if (k >> i) & 1 else lo[i] for i in range(3)] for k in range(8)])
    for q in [corners] if _moved_mm(T, corners) <= limit_mm else (
            points_mm[at:at + CLOSEST_CHUNK] for at in range(0, len(points_mm), CLOSEST_CHUNK)):
        if _moved_mm(T, q) > limit_mm:
            return True
    return False


def _moved_mm(T: np.ndarray, points_mm: np.ndarray) -> float:
    delta = transform_points(T, points_mm) - points_mm
    return float(np.sqrt(np.einsum("ij,ij->i", delta, delta).max()))


def _best_fit_result(surface: CadSurface, p: np.ndarray, cfg: InspectionConfig, closest: ClosestPoints | None = None
                     ) -> tuple[BestFit | None, str]:
    """The best fit and its deviations, or (None, why) when it cannot be made; the as-measured result
    stands on its own either way. ``closest``: the points' :meth:`CadSurface.closest` where known (then a
    small fit updates the deviations, :func:`signed_distance_moved`)."""
    try:
        T, its, converged, used = best_fit(surface, p, cfg.best_fit_max_distance_mm, cfg.best_fit_iterations)
    except InspectionError as e:
        log.warning("%s", e)
        return None, str(e)
    if not converged:
        log.warning("best fit did not converge in %d iterations", its)
    d_fit = (surface.signed_distance(transform_points(T, p)) if closest is None
             else signed_distance_moved(surface, p, T, closest))
    lo, hi = cfg.tolerance_lower_mm, cfg.tolerance_upper_mm
    fit = BestFit(
        T_F_M=T,
        translation_mm=float(np.linalg.norm(T[:3, 3])),
        rotation_deg=float(np.degrees(rotation_angle(T))),
        iterations=its,
        converged=converged,
        used_points=used,
        deviations_mm=d_fit,
        stats=DeviationStats.of(d_fit),
        tolerance=ToleranceResult.of(d_fit, lo, hi),
    )
    return fit, ""


def inspect_cloud(
    points_mm: np.ndarray,
    mesh: o3d.geometry.TriangleMesh | CadSurface,
    cfg: InspectionConfig | None = None,
) -> InspectionResult:
    """Deviation of a measured cloud (frame F, mm) from the CAD mesh, by ``cfg`` (tolerance, regions, fit)."""
    cfg = cfg or InspectionConfig()
    p = as_points(points_mm)
    surface = mesh if isinstance(mesh, CadSurface) else CadSurface(mesh)
    closest = surface.closest(p)
    d = closest.signed_mm
    lo, hi = cfg.tolerance_lower_mm, cfg.tolerance_upper_mm
    masks = [(region.name, region_mask(p, region)) for region in cfg.regions]
    if cfg.mesh_group_regions:
        masks += surface.group_masks(closest.triangle_ids)
    regions = [RegionResult(name, DeviationStats.of(d[m]), ToleranceResult.of(d[m], lo, hi)) for name, m in masks]
    with ThreadPoolExecutor(1, thread_name_prefix="best-fit") as pool:  # the fit while the areas are found
        fit = pool.submit(_best_fit_result, surface, p, cfg, closest) if cfg.best_fit else None
        stats = DeviationStats.of(d)
        tol = ToleranceResult.of(d, lo, hi)
        assert stats is not None and tol is not None  # p has at least one point
        areas = find_deviation_areas(p, d, lo, hi, cfg.area_smoothing_mm, cfg.area_min_mm2)
        fit, note = fit.result() if fit is not None else (None, "")
    log.info(
        "inspected %d points: mean %.4f mm, sigma %.4f mm, %.1f %% in tolerance, %d areas beyond it",
        stats.count, stats.mean_mm, stats.sigma_mm, tol.in_pct, len(areas),
    )
    return InspectionResult(p, d, closest.normals, stats, tol, tuple(regions), fit, note, areas,
                            closest.triangle_ids)
