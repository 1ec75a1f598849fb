"""Deviation of a measured cloud from its CAD mesh: signed distances, statistics, tolerances, best fit.

Frames and units: the cloud and the mesh are both in the part/CAD frame F, millimetres. A deviation is the
signed distance from a point to the closest point of the CAD surface, positive on the side the surface's
outward normal points to (material above the design), negative below it.

Open3D's ``RaycastingScene`` works in float32. The mesh is therefore shifted to its bounding-box centre
before it is handed over and every query is shifted the same way, which keeps the rounding error of a
3 m part at about 0.1 um; distances and signs are then formed in float64.
"""

from __future__ import annotations

import functools
import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import open3d as o3d
from tandemscan.config.models import RegionConfig
from tandemscan.pipeline.geometry.frames import (
    from_rotvec,
    invert,
    rotate_vectors,
    rotation_angle,
    to_rotvec,
    transform_points,
)
from tandemscan.pipeline.geometry.part import enclosed_volume_mm3, triangles_closed
from tandemscan.pipeline.geometry.units import box_mm, in_box_mm
from tandemscan.pipeline.inspection.cad_orientation import MeshPatches, mesh_patches
from tandemscan.pipeline.inspection.decision import DecisionRule, RuleName
from tandemscan.pipeline.inspection.deviation_areas import DeviationArea, DeviationCloud, find_deviation_areas
from tandemscan.pipeline.parameters import FromSection

if TYPE_CHECKING:
    from tandemscan.pipeline.inspection.verdict import Judgement

log = logging.getLogger(__name__)


class InspectionError(ValueError):
    """Bad input to the inspection: an empty cloud, a mesh without triangles, non-finite points."""


@dataclass(frozen=True)
class InspectionCriteria(FromSection):
    """What a cloud is inspected and judged by: ``[inspection]``'s keys of the same names
    (``InspectionCriteria.from_section(cfg)``; mm). The tolerance band (``tolerance_lower_mm``,
    ``tolerance_upper_mm``, signed: + = material outside the CAD surface) and the decision rule with its coverage
    factor (``decision_rule``, ``decision_k``: :attr:`rule`); the regions reported apart (``regions``, and one a
    mesh material group with ``mesh_group_regions``); the best fit reported beside the result (``best_fit``, on
    the points within ``best_fit_max_distance_mm``, ``best_fit_iterations``); deviation areas (deviations averaged
    over ``area_smoothing_mm``, none smaller than ``area_min_mm2``)."""

    tolerance_lower_mm: float
    tolerance_upper_mm: float
    decision_rule: RuleName
    decision_k: float
    regions: tuple[RegionConfig, ...]
    mesh_group_regions: bool
    best_fit: bool
    best_fit_max_distance_mm: float
    best_fit_iterations: int
    area_smoothing_mm: float
    area_min_mm2: float

    @property
    def rule(self) -> DecisionRule:
        """The decision rule ``decision_rule`` with ``decision_k`` names."""
        return DecisionRule(self.decision_rule, self.decision_k)


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


#: a point pairs with no face of a closed solid that turns away from where the point was seen from by more than
#: about 107 deg (its outward normal's cosine with that direction below -this)
BEHIND_COS = 0.3


@dataclass(frozen=True)
class SeenFrom:
    """Where the points of a fit were seen from and which way the CAD's closed solids face: a point cannot lie on
    a face of a closed solid whose outside turns away from the scanner that saw it (it would be the far side of a
    wall, seen through the material), so :func:`best_fit` does not pair it there: the two skins of a thin plate
    or shell are told apart (docs/inspection-method.md, "Alignment").

    ``toward`` (N, 3): unit directions from each point toward where it was seen from, in the points' own frame
    (a scanner's normals; zero where unknown); ``outward`` (T,): per CAD triangle +1 where the surface's normal
    points out of its closed solid, -1 where it points in, 0 on an open patch (no inside to tell)."""

    toward: np.ndarray
    outward: np.ndarray

    def rows(self, rows) -> SeenFrom:
        """The same for the points ``rows`` (an index array or a slice) of the cloud."""
        return SeenFrom(self.toward[rows], self.outward)

    def behind(self, T_F_M: np.ndarray, cp: ClosestPoints) -> np.ndarray:
        """(N,) bool: the points (placed by ``T_F_M``, closest CAD points ``cp``) on the back of a closed face."""
        facing = np.einsum("ij,ij->i", cp.normals, rotate_vectors(T_F_M, self.toward))
        return self.outward[cp.triangle_ids] * facing < -BEHIND_COS


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
    """The CAD mesh as a distance field: closest points and signed distances of queries, frame F, mm.

    The sign follows the mesh's winding; a closed mesh wound inside out is taken reversed. ``reversed``
    (T,) bool reverses the chosen triangles instead (:mod:`tandemscan.pipeline.inspection.cad_orientation`:
    an open or inconsistently wound mesh oriented by the measured side, :meth:`oriented`)."""

    def __init__(self, mesh: o3d.geometry.TriangleMesh, reversed: np.ndarray | None = None):
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        triangles = np.asarray(mesh.triangles, dtype=np.int64)
        if len(triangles) == 0 or len(vertices) < 3:
            raise InspectionError("CAD mesh has no triangles")
        if not np.isfinite(vertices).all():
            raise InspectionError("CAD mesh has non-finite vertices")
        self.mesh = mesh
        self.origin_mm = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
        local = (vertices - self.origin_mm).astype(np.float32)
        if reversed is not None:
            self.reversed = np.asarray(reversed, bool)
        elif triangles_closed(triangles) and enclosed_volume_mm3(local, triangles) < 0.0:
            log.warning("CAD mesh is wound inside out (negative volume); using its triangles reversed")
            self.reversed = np.ones(len(triangles), bool)  # its normals would point into the material
        else:
            self.reversed = np.zeros(len(triangles), bool)
        self.flipped = bool(self.reversed.all())
        triangles = np.where(self.reversed[:, None], triangles[:, ::-1], triangles)
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.core.Tensor(local), o3d.core.Tensor(triangles.astype(np.uint32)))

    def oriented(self, reversed: np.ndarray) -> CadSurface:
        """This surface with the triangles ``reversed`` (T,) bool wound against the file (itself where that is
        how it is wound already)."""
        if np.array_equal(reversed, self.reversed):
            return self
        turned = CadSurface(self.mesh, reversed)
        if "patches" in self.__dict__:  # of the same mesh: not computed again
            turned.patches = self.patches
        return turned

    @functools.cached_property
    def patches(self) -> MeshPatches:
        """The mesh's connected patches as its file winds them (:func:`cad_orientation.mesh_patches`), computed once
        for the alignment's viewing side and the measured side's winding."""
        return mesh_patches(np.asarray(self.mesh.vertices), np.asarray(self.mesh.triangles))

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
        """(N,) signed distance of every point to the surface, mm (+ outside along the outward normal): those of
        :meth:`closest`, asked a chunk at a time, so that only the distances of the whole cloud are held."""
        p = as_points(points_mm)
        out = np.empty(len(p))
        for lo in range(0, len(p), CLOSEST_CHUNK):
            out[lo:lo + CLOSEST_CHUNK] = self.closest(p[lo:lo + CLOSEST_CHUNK]).signed_mm
        return out


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
    #: the points and deviations with their KD tree and areas' screening, built once for the band and the verdict's
    #: guard band (``verdict.judge``): they go with this result
    deviation_cloud: DeviationCloud = field(repr=False, compare=False)
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
    return in_box_mm(points_mm, region.min_mm, region.max_mm)


@dataclass(frozen=True)
class SurfaceFit:
    """One robust fit of points (frame M) to the CAD surface (frame F): :func:`best_fit`'s result.

    ``T_F_M`` places the points; ``cost_mm2`` is the mean robust cost per sampled point at the end (half the
    squared residual inside the Huber threshold, linear beyond it, constant beyond the trim distance);
    ``used_points`` are the sampled points within the trim distance. ``normal_matrix`` is the data's 6x6
    ``J^T W J`` at the end for a small motion ``(t mm, r rad)`` of the points about ``centre_mm`` (frame F:
    ``p -> p + r x (p - centre) + t``), ``scale`` what makes its rotations comparable with its translations, and
    ``sigma_mm`` the weighted RMS residual of the used points: the
    alignment turns them into its observability and covariance (docs/inspection-method.md, "Alignment")."""

    T_F_M: np.ndarray
    iterations: int
    converged: bool
    used_points: int
    sampled_points: int
    cost_mm2: float
    normal_matrix: np.ndarray = field(repr=False)
    centre_mm: np.ndarray = field(repr=False)
    scale: np.ndarray = field(repr=False)  # (6,) 1, 1, 1 and the points' RMS radius about the centre (mm) thrice
    sigma_mm: float = float("nan")


#: the prior's spring (:func:`best_fit`): its stiffness per sampled point against a point's own ``n n^T``,
#: so weak that a direction the surface fixes at 1e-5 of the strongest one moves by under 1e-5 of the
#: distance to the prior, and strong enough to hold a direction the surface does not fix at all
PRIOR_STIFFNESS = 1e-10
MAX_STEP_RAD = 0.2  # a Levenberg-Marquardt step turns the points by at most this much (and moves them by the trim)


def _robust_cost(r: np.ndarray, trim_mm: float, huber_mm: float | None) -> np.ndarray:
    """Per-point cost (mm^2) of residuals ``r``: ``r^2/2`` (Huber's linear tail beyond ``huber_mm``), held
    constant beyond ``trim_mm``: the same function of the pose for every point, near or far."""
    a = np.minimum(np.abs(r), trim_mm)
    if huber_mm is None or huber_mm >= trim_mm:
        return 0.5 * a * a
    return np.where(a <= huber_mm, 0.5 * a * a, huber_mm * a - 0.5 * huber_mm * huber_mm)


EDGE_MIN_MM = 0.1  # a point this far from an edge or a corner (off the normal by 8 deg) pairs along its direction


def _pairs(surface: CadSurface, q: np.ndarray, seen: SeenFrom | None = None, T_F_M: np.ndarray | None = None
           ) -> tuple[np.ndarray, np.ndarray]:
    """Residual (mm) and its unit gradient (the direction a point moves to lengthen it) of every point of
    ``q`` (frame F): the signed distance and the closest triangle's normal on a face, the distance and the
    direction from the closest point where that is an edge or a corner, so a slide off the mesh's boundary
    is seen; infinite where ``seen`` (the points' directions, placed by ``T_F_M``) puts the point on the back
    of a closed face (:class:`SeenFrom`): no pair."""
    cp = surface.closest(q)
    r, g = cp.signed_mm.copy(), cp.normals.copy()
    off = np.abs(r) > EDGE_MIN_MM  # nearer, float32's closest points leave the direction uncertain
    to_point = (q[off] - cp.points_mm[off]) / np.abs(r[off])[:, None]
    edge = np.abs(np.einsum("ij,ij->i", to_point, g[off])) < 0.99
    at = np.flatnonzero(off)[edge]
    g[at], r[at] = to_point[edge], np.abs(r[at])
    if seen is not None:
        r[seen.behind(T_F_M, cp)] = np.inf
    return r, g


def _twist(D: np.ndarray, centre_mm: np.ndarray) -> np.ndarray:
    """A rigid motion ``D`` (frame F) as ``(t mm, r rad)`` about ``centre_mm``: how far it moves the centre and
    its rotation vector."""
    return np.r_[transform_points(D, centre_mm[None])[0] - centre_mm, to_rotvec(D)[1]]


def _motion(x: np.ndarray, centre_mm: np.ndarray) -> np.ndarray:
    """The rigid motion (4x4, frame F) turning by ``x[3:]`` rad about ``centre_mm`` and moving it by ``x[:3]`` mm."""
    step = from_rotvec(x[:3], x[3:])
    step[:3, 3] += centre_mm - step[:3, :3] @ centre_mm
    return step


def best_fit(
    surface: CadSurface,
    points_mm: np.ndarray,
    max_distance_mm: float,
    iterations: int = 30,
    tolerance_mm: float = 1e-5,
    max_points: int = 50_000,
    *,
    start: np.ndarray | None = None,
    huber_mm: float | None = None,
    prior: np.ndarray | None = None,
    seen: SeenFrom | None = None,
) -> SurfaceFit:
    """Robust point-to-plane fit of ``points_mm`` (frame M) onto the CAD surface itself, by damped Gauss-Newton
    (Levenberg-Marquardt) from ``start`` (``T_F_M``, default identity).

    The cost is :func:`_robust_cost` summed over the same points at every pose (at most ``max_points``, an
    even subsample): a point further than ``max_distance_mm`` from the surface costs the same wherever it is
    (a trimmed fit: outliers and form errors beyond it do not pull), one within ``huber_mm`` quadratically.
    A step is taken only where it lowers that cost (else the damping grows and the step shrinks), turns by at
    most :data:`MAX_STEP_RAD` and moves by at most ``max_distance_mm``. ``prior`` (``T_F_M``, default the
    start) holds, by a spring of :data:`PRIOR_STIFFNESS`, the directions the surface does not fix (the axis of
    a cylinder, an extrusion): they stay where the prior puts them instead of drifting. Converged: a step
    moving no point by more than ``tolerance_mm``, or no step lowering the cost any more. ``seen``: where the
    points were seen from (:class:`SeenFrom`); a point on the back of a closed face costs as one beyond the trim.

    Ten parameters: the surface and the points, the fit's gate, then solver options with defaults (iterations,
    tolerance, thinning; keyword-only: start, Huber scale, prior, viewing side).
    """
    p = np.asarray(points_mm)
    thin = slice(None, None, max(1, int(np.ceil(len(p) / max_points))))
    p = as_points(p[thin])
    seen = None if seen is None else seen.rows(thin)
    T = np.eye(4) if start is None else np.array(start, dtype=np.float64)
    T_prior = T.copy() if prior is None else np.asarray(prior, float)
    n = len(p)
    q = transform_points(T, p)
    centre = q.mean(axis=0)
    extent = max(float(np.sqrt(np.mean(np.sum((q - centre) ** 2, axis=1)))), 1.0)
    scale = np.r_[1.0, 1.0, 1.0, extent, extent, extent]  # rotation as mm at the cloud's RMS radius
    spring = PRIOR_STIFFNESS * n * np.diag(scale**2)

    def evaluate(T_: np.ndarray):
        q_ = transform_points(T_, p)
        r_, g_ = _pairs(surface, q_, seen, T_)
        e = _twist(T_ @ invert(T_prior), centre)
        return q_, r_, g_, float(_robust_cost(r_, max_distance_mm, huber_mm).sum() + 0.5 * e @ spring @ e), e

    q, r, g, cost, e = evaluate(T)
    mu, steps, converged = 1e-4, 0, False
    while steps < iterations and not converged:
        steps += 1
        keep = np.abs(r) <= max_distance_mm
        if int(keep.sum()) < 6:
            raise InspectionError(f"best fit: only {int(keep.sum())} points within {max_distance_mm} mm of the "
                                  "CAD surface")
        H, b = _normal_equations(q[keep], g[keep], r[keep], centre, huber_mm)
        b += spring @ e
        accepted = False
        while mu < 1e8 and not accepted:
            x = -np.linalg.solve(H + spring + mu * n * np.diag(scale**2), b)
            x *= min(1.0, max_distance_mm / max(float(np.linalg.norm(x[:3])), 1e-12),
                     MAX_STEP_RAD / max(float(np.linalg.norm(x[3:])), 1e-12))
            T_new = _motion(x, centre) @ T
            trial = evaluate(T_new)
            if trial[3] <= cost:
                T, (q, r, g, cost, e), accepted = T_new, trial, True
                mu = max(mu / 10.0, 1e-12)
            else:
                mu *= 10.0
        converged = not accepted or float(np.linalg.norm(x[:3]) + np.linalg.norm(x[3:]) * extent) < tolerance_mm
    keep = np.abs(r) <= max_distance_mm
    used = int(keep.sum())
    H, _ = _normal_equations(q[keep], g[keep], r[keep], centre, huber_mm)
    w = _irls_weights(r[keep], huber_mm)
    sigma = float(np.sqrt(np.sum(w * r[keep] ** 2) / max(float(w.sum()) - 6.0, 1.0))) if used > 6 else float("nan")
    return SurfaceFit(T, steps, converged, used, n, cost / n, H, centre, scale, sigma)


def _irls_weights(r: np.ndarray, huber_mm: float | None) -> np.ndarray:
    """Gauss-Newton weights of :func:`_robust_cost` inside the trim: 1, Huber's ``huber_mm / |r|`` beyond it."""
    if huber_mm is None:
        return np.ones_like(r)
    return np.minimum(1.0, huber_mm / np.maximum(np.abs(r), 1e-12))


def _normal_equations(q: np.ndarray, g: np.ndarray, r: np.ndarray, centre: np.ndarray, huber_mm: float | None
                      ) -> tuple[np.ndarray, np.ndarray]:
    """``J^T W J`` (6x6) and ``J^T W r`` of residuals ``r`` with unit gradients ``g`` at points ``q`` (frame F)
    for a small motion ``(t mm, r rad)`` about ``centre``: ``J = [g, (q - centre) x g]``, IRLS weights."""
    w = _irls_weights(r, huber_mm)
    J = np.hstack([g, np.cross(q - centre, g)])
    return (J * w[:, None]).T @ J, J.T @ (w * r)


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
    lo, hi = box_mm(points_mm)
    corners = np.array([[hi[i] if (k >> i) & 1 else lo[i] for i in range(3)] for k in range(8)])
    for q in [corners] if _moved_mm(T, corners) <= limit_mm else (
            points_mm[at:at + CLOSEST_CHUNK] for at in range(0, len(points_mm), CLOSEST_CHUNK)):
        if _moved_mm(T, q) > limit_mm:
            return True
    return False


def _moved_mm(T: np.ndarray, points_mm: np.ndarray) -> float:
    delta = transform_points(T, points_mm) - points_mm
    return float(np.sqrt(np.einsum("ij,ij->i", delta, delta).max()))


def _best_fit_result(surface: CadSurface, p: np.ndarray, criteria: InspectionCriteria,
                     closest: ClosestPoints | None = None) -> tuple[BestFit | None, str]:
    """The best fit and its deviations, or (None, why) when it cannot be made; the as-measured result
    stands on its own either way. ``closest``: the points' :meth:`CadSurface.closest` where known (then a
    small fit updates the deviations, :func:`signed_distance_moved`)."""
    try:
        sf = best_fit(surface, p, criteria.best_fit_max_distance_mm, criteria.best_fit_iterations)
    except InspectionError as e:
        log.warning("%s", e)
        return None, str(e)
    T = sf.T_F_M
    if not sf.converged:
        log.warning("best fit did not converge in %d iterations", sf.iterations)
    d_fit = (surface.signed_distance(transform_points(T, p)) if closest is None
             else signed_distance_moved(surface, p, T, closest))
    lo, hi = criteria.tolerance_lower_mm, criteria.tolerance_upper_mm
    return BestFit(
        T_F_M=T,
        translation_mm=float(np.linalg.norm(T[:3, 3])),
        rotation_deg=float(np.degrees(rotation_angle(T))),
        iterations=sf.iterations,
        converged=sf.converged,
        used_points=sf.used_points,
        deviations_mm=d_fit,
        stats=DeviationStats.of(d_fit),
        tolerance=ToleranceResult.of(d_fit, lo, hi),
    ), ""


def inspect_cloud(
    points_mm: np.ndarray,
    mesh: o3d.geometry.TriangleMesh | CadSurface,
    criteria: InspectionCriteria,
    closest: ClosestPoints | None = None,
    find_areas: bool = True,
) -> InspectionResult:
    """Deviation of a measured cloud (frame F, mm) from the CAD mesh, by ``criteria`` (tolerance, regions, fit);
    ``closest``: the CAD surface's closest points to the cloud where the caller has them (``CadSurface.closest``);
    ``find_areas`` False: no deviation areas sought (a sample of a tiled cloud, whose areas the tiles find)."""
    p = as_points(points_mm)
    surface = mesh if isinstance(mesh, CadSurface) else CadSurface(mesh)
    closest = surface.closest(p) if closest is None else closest
    d = closest.signed_mm
    cloud = DeviationCloud(p, d)
    lo, hi = criteria.tolerance_lower_mm, criteria.tolerance_upper_mm
    masks = [(region.name, region_mask(p, region)) for region in criteria.regions]
    if criteria.mesh_group_regions:
        masks += surface.group_masks(closest.triangle_ids)
    regions = [RegionResult(name, DeviationStats.of(d[m]), ToleranceResult.of(d[m], lo, hi)) for name, m in masks]
    with ThreadPoolExecutor(1, thread_name_prefix="best-fit") as pool:  # the fit while the areas are found
        fit = pool.submit(_best_fit_result, surface, p, criteria, closest) if criteria.best_fit else None
        stats = DeviationStats.of(d)
        tol = ToleranceResult.of(d, lo, hi)
        assert stats is not None and tol is not None  # p has at least one point
        areas = (find_deviation_areas(cloud, lo, hi, criteria.area_smoothing_mm, criteria.area_min_mm2)
                 if find_areas else ())
        fit, note = fit.result() if fit is not None else (None, "")
    log.info(
        "inspected %d points: mean %.4f mm, sigma %.4f mm, %.1f %% in tolerance, %d areas beyond it",
        stats.count, stats.mean_mm, stats.sigma_mm, tol.in_pct, len(areas),
    )
    return InspectionResult(p, d, closest.normals, stats, tol, tuple(regions), fit, cloud, note, areas,
                            closest.triangle_ids)
