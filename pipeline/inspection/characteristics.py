"""A part's characteristics evaluated on one inspected cloud: surface profile, flatness, sections and edge
positions, each with its actual value, expanded uncertainty U and status by the decision rule
(docs/inspection.md, "Inspection templates"; the rule: :mod:`tandemscan.pipeline.inspection.decision`).

Frame F (CAD), millimetres. Per-point deviations are averaged over the template's ``smoothing_mm`` before a
worst is taken (a noise peak of one point is no defect, as for the deviation areas); the raw per-point
deviations of a surface profile are kept (the QIF results carry them). A characteristic's U is the largest
per-point U among the points its actual comes from (conservative: the averaging would lower it).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from tandemscan.config.inspection_template import (
    EdgeSpec,
    FlatnessSpec,
    InspectionTemplate,
    PatchSpec,
    SectionSpec,
    SurfaceProfileSpec,
)
from tandemscan.pipeline.geometry.units import in_box_mm
from tandemscan.pipeline.inspection.decision import DecisionRule, Tolerance, combine, decide
from tandemscan.pipeline.inspection.deviation_areas import even_centres, local_deviation
from tandemscan.pipeline.inspection.inspect import CadSurface, InspectionError

log = logging.getLogger(__name__)

MIN_POINTS = 20  # fewer measured points in a characteristic's region: not measured
CAD_SAMPLES_PER_MM2 = 4.0  # an edge's CAD side is found on the mesh sampled this densely
CENTRE_CELL = 0.75  # averaged deviations are taken at one point per cube of this many smoothing radii


@dataclass(frozen=True)
class SectionCurve:
    """A section's deviations along the CAD intersection curve: arc length from the curve's start (mm) and
    the averaged deviation there (mm), sorted by arc length."""

    arc_mm: np.ndarray
    deviation_mm: np.ndarray


@dataclass(frozen=True)
class CharacteristicResult:
    """One characteristic on one cloud: ``actual_mm`` against ``[lower_mm, upper_mm]`` with the expanded
    uncertainty ``uncertainty_mm`` and the rule's ``status`` (pass, fail, indeterminate or not measured).

    ``worst_plus_mm``/``worst_minus_mm``: the largest and smallest averaged value (profile and sections:
    deviation; flatness: distance from the plane; edge: both the actual). ``at_mm``: where the actual is
    (frame F). ``point_ids`` index the inspected cloud's points that entered; ``deviations_mm`` are their
    raw per-point values (the surface profile's per-point deviations)."""

    id: str
    name: str
    kind: str
    method: str
    actual_mm: float
    lower_mm: float
    upper_mm: float
    uncertainty_mm: float
    status: str
    reason: str
    points: int
    worst_plus_mm: float
    worst_minus_mm: float
    at_mm: tuple[float, float, float]
    point_ids: np.ndarray = field(repr=False)
    deviations_mm: np.ndarray = field(repr=False)
    curve: SectionCurve | None = field(default=None, repr=False)
    direction: tuple[float, float, float] | None = None  # a section's plane normal; an edge's into the opening

    def summary(self) -> dict:
        """JSON-ready (report.json ``inspection.characteristics``): every figure but the per-point arrays."""
        return {"id": self.id, "name": self.name, "kind": self.kind, "method": self.method,
                "actual_mm": self.actual_mm, "lower_mm": self.lower_mm, "upper_mm": self.upper_mm,
                "uncertainty_mm": self.uncertainty_mm, "status": self.status, "reason": self.reason,
                "points": self.points, "worst_plus_mm": self.worst_plus_mm, "worst_minus_mm": self.worst_minus_mm,
                "at_mm": list(self.at_mm)}


@dataclass(frozen=True)
class MeasuredCloud:
    """What the characteristics are evaluated on: the inspected points (frame F, mm), their signed deviations
    from CAD, closest CAD triangles, per-point expanded uncertainty (mm) and the CAD surface."""

    points_mm: np.ndarray
    deviations_mm: np.ndarray
    triangle_ids: np.ndarray
    uncertainty_mm: np.ndarray
    surface: CadSurface

    def rows(self, rows: slice) -> MeasuredCloud:
        """The points ``rows`` of the cloud (views), against the same surface."""
        return MeasuredCloud(self.points_mm[rows], self.deviations_mm[rows], self.triangle_ids[rows],
                             self.uncertainty_mm[rows], self.surface)


def patch_mask(cloud: MeasuredCloud, patch: PatchSpec) -> np.ndarray:
    """(N,) bool: the points in the patch's box (inclusive) and, when it names face groups, on them."""
    p = cloud.points_mm
    inside = np.ones(len(p), bool)
    if patch.min_mm is not None:
        inside &= in_box_mm(p, patch.min_mm, patch.max_mm)
    if patch.face_groups:
        groups = np.asarray(cloud.surface.mesh.triangle_material_ids)
        if len(groups) != len(cloud.surface.mesh.triangles):
            raise InspectionError("the template selects face groups but the CAD mesh has none")
        inside &= np.isin(groups[cloud.triangle_ids], patch.face_groups)
    return inside


def _smoothed(points_mm: np.ndarray, values_mm: np.ndarray, radius_mm: float, at: np.ndarray | None = None
              ) -> np.ndarray:
    """The values averaged over their neighbours (among ``points_mm``) within ``radius_mm``, at the points
    ``at`` (indices; default: an even thinning, one point per cube of :data:`CENTRE_CELL` radii: the worst of
    the averages is found to that, for a ninth of the work at 1 mm spacing and 4 mm radius)."""
    if at is None:
        at = even_centres(points_mm, CENTRE_CELL * radius_mm)
    return at, local_deviation(points_mm, values_mm, radius_mm, at).smoothed_mm


def _decided(spec, actual: float, u: float, rule: DecisionRule, also: float | None = None) -> tuple[str, str]:
    """(status, reason) of ``actual`` (and, for a two-sided worst, ``also``) against the spec's limits."""
    tol = Tolerance(spec.lower_mm, spec.upper_mm)
    first = decide(actual, tol, u, rule, what=f"{spec.id} {spec.name}")
    if also is None:
        return first.verdict, first.reason
    second = decide(also, tol, u, rule, what=f"{spec.id} {spec.name}")
    status = combine([first.verdict, second.verdict])
    return status, first.reason if first.verdict == status else second.reason


def _not_measured(spec, kind: str, method: str, n: int, why: str) -> CharacteristicResult:
    nan = float("nan")
    return CharacteristicResult(spec.id, spec.name, kind, method, nan, spec.lower_mm, spec.upper_mm, nan,
                                "not measured", why, n, nan, nan, (nan, nan, nan), np.zeros(0, np.int64),
                                np.zeros(0))


def _worst_deviation(spec, kind: str, method: str, cloud: MeasuredCloud, ids: np.ndarray, at: np.ndarray,
                     smoothed: np.ndarray, rule: DecisionRule, curve: SectionCurve | None = None
                     ) -> CharacteristicResult:
    """A two-sided deviation characteristic from the averaged deviations ``smoothed`` at the points
    ``ids[at]``: the worst positive and negative, actual = the larger in magnitude, both decided.

    Nine parameters: the characteristic (spec, kind, method), the cloud and its points that count (``ids``, ``at``),
    their averaged deviations, the rule, and the section curve where there is one."""
    hi, lo = int(np.argmax(smoothed)), int(np.argmin(smoothed))
    worst, other = (hi, lo) if abs(smoothed[hi]) >= abs(smoothed[lo]) else (lo, hi)
    u = float(max(cloud.uncertainty_mm[ids[at[hi]]], cloud.uncertainty_mm[ids[at[lo]]]))
    status, reason = _decided(spec, float(smoothed[worst]), u, rule, also=float(smoothed[other]))
    return CharacteristicResult(spec.id, spec.name, kind, method, float(smoothed[worst]), spec.lower_mm,
                                spec.upper_mm, u, status, reason, len(ids), float(smoothed[hi]), float(smoothed[lo]),
                                tuple(map(float, cloud.points_mm[ids[at[worst]]])), ids, cloud.deviations_mm[ids],
                                curve)


def surface_profile(spec: SurfaceProfileSpec, template: InspectionTemplate, cloud: MeasuredCloud,
                    rule: DecisionRule) -> CharacteristicResult:
    """ISO 1101 profile of the region: worst positive and negative averaged deviation; actual = the larger
    in magnitude; status: both against the limits."""
    method = f"deviation from CAD averaged over {template.smoothing_mm:g} mm, worst"
    ids = np.flatnonzero(patch_mask(cloud, template.region(spec.region)))
    if len(ids) < MIN_POINTS:
        return _not_measured(spec, "surface_profile", method, len(ids), f"{len(ids)} points in the region")
    at, s = _smoothed(cloud.points_mm[ids], cloud.deviations_mm[ids], template.smoothing_mm)
    return _worst_deviation(spec, "surface_profile", method, cloud, ids, at, s, rule)


def flatness(spec: FlatnessSpec, template: InspectionTemplate, cloud: MeasuredCloud,
             rule: DecisionRule) -> CharacteristicResult:
    """Flatness: the range of the points' distances from their least-squares plane, averaged over the
    smoothing radius (a least-squares reference plane, not the minimum zone: it can only read larger)."""
    method = f"least-squares plane, range of the distances averaged over {template.smoothing_mm:g} mm"
    ids = np.flatnonzero(patch_mask(cloud, template.region(spec.region)))
    if len(ids) < MIN_POINTS:
        return _not_measured(spec, "flatness", method, len(ids), f"{len(ids)} points in the region")
    p = cloud.points_mm[ids]
    centre = p.mean(axis=0)
    normal = np.linalg.svd(p - centre, full_matrices=False)[2][2]
    r = (p - centre) @ normal
    at, s = _smoothed(p, r, template.smoothing_mm)
    hi, lo = int(np.argmax(s)), int(np.argmin(s))
    actual = float(s[hi] - s[lo])
    u = float(np.hypot(cloud.uncertainty_mm[ids[at[hi]]], cloud.uncertainty_mm[ids[at[lo]]]))
    status, reason = _decided(spec, actual, u, rule)
    return CharacteristicResult(spec.id, spec.name, "flatness", method, actual, spec.lower_mm, spec.upper_mm, u,
                                status, reason, len(ids), float(s[hi]), float(s[lo]), tuple(map(float, p[at[hi]])),
                                ids, r)


def _plane_basis(normal) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    n = np.asarray(normal, float)
    n = n / np.linalg.norm(n)
    e1 = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return n, e1, np.cross(n, e1)


def cad_section(surface: CadSurface, point_mm, normal) -> np.ndarray:
    """(M, 3) points of the CAD surface's intersection with the plane (frame F, mm): where the mesh edges
    cross it, ordered by their angle about the section's centre in the plane (a star-shaped section)."""
    n, e1, e2 = _plane_basis(normal)
    v = np.asarray(surface.mesh.vertices, float)
    e = np.asarray(surface.mesh.triangles)
    h = (v - np.asarray(point_mm, float)) @ n
    edges = np.unique(np.sort(np.concatenate([e[:, [0, 1]], e[:, [1, 2]], e[:, [2, 0]]]), axis=1), axis=0)
    a, b = edges[:, 0], edges[:, 1]
    crossing = (h[a] > 0) != (h[b] > 0)
    a, b = a[crossing], b[crossing]
    t = h[a] / (h[a] - h[b])
    x = v[a] + t[:, None] * (v[b] - v[a])
    if len(x) < 3:
        raise InspectionError(f"the section plane through {tuple(point_mm)} does not cut the CAD surface")
    rel = x - x.mean(axis=0)
    return x[np.argsort(np.arctan2(rel @ e2, rel @ e1))]


def section(spec: SectionSpec, template: InspectionTemplate, cloud: MeasuredCloud,
            rule: DecisionRule) -> CharacteristicResult:
    """The averaged deviations of the points within ``half_width_mm`` of the plane, along the CAD section
    curve (arc length of each point's closest CAD point projected onto the plane); actual = the worst."""
    method = f"deviation within {spec.half_width_mm:g} mm of the plane, averaged over {template.smoothing_mm:g} mm"
    n, e1, e2 = _plane_basis(spec.normal)
    dist = (cloud.points_mm - np.asarray(spec.point_mm)) @ n
    pool = np.abs(dist) <= max(spec.half_width_mm, template.smoothing_mm)
    if spec.region is not None:
        pool &= patch_mask(cloud, template.region(spec.region))
    pool_ids = np.flatnonzero(pool)
    on = np.abs(dist[pool_ids]) <= spec.half_width_mm
    ids = pool_ids[on]
    if len(ids) < MIN_POINTS:
        return replace(_not_measured(spec, "section", method, len(ids), f"{len(ids)} points within the section"),
                       direction=tuple(map(float, n)))
    on_at = np.flatnonzero(on)
    _, s = _smoothed(cloud.points_mm[pool_ids], cloud.deviations_mm[pool_ids], template.smoothing_mm, on_at)
    curve = cad_section(cloud.surface, spec.point_mm, spec.normal)
    centre = curve.mean(axis=0)
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(curve, axis=0), axis=1))]
    angle_curve = np.arctan2((curve - centre) @ e2, (curve - centre) @ e1)
    q = cloud.points_mm[ids] - centre
    along = np.interp(np.arctan2(q @ e2, q @ e1), angle_curve, arc)
    order = np.argsort(along)
    return replace(_worst_deviation(spec, "section", method, cloud, ids, np.arange(len(ids)), s, rule,
                                    SectionCurve(along[order], s[order])), direction=tuple(map(float, n)))


@dataclass(frozen=True)
class EdgeFrame:
    """Coordinates about a CAD edge: origin at its middle, ``along`` the edge, ``into`` the opening in the
    surface and the surface ``normal`` outside it (frame F); ``half_length_mm`` of the edge."""

    origin: np.ndarray
    along: np.ndarray
    into: np.ndarray
    normal: np.ndarray
    half_length_mm: float

    def coordinates(self, points_mm: np.ndarray) -> np.ndarray:
        """(N, 3): along the edge, into the opening and above the surface, mm."""
        q = np.asarray(points_mm, float) - self.origin
        return np.column_stack([q @ self.along, q @ self.into, q @ self.normal])

    def taken_half_mm(self, corridor_mm: float) -> np.ndarray:
        """(3,) half extents (mm; along, into, normal: :meth:`coordinates`) of the box the edge takes its points
        from: short of its ends by ``corridor_mm`` (where the walls of a corner meet; at least half its length), a
        corridor either side of it, two above and below the surface."""
        return np.array([max(self.half_length_mm - corridor_mm, 0.5 * self.half_length_mm), corridor_mm,
                         2.0 * corridor_mm])


def edge_frame(spec: EdgeSpec, surface: CadSurface) -> EdgeFrame:
    """The edge's frame: its ends projected onto the CAD surface, the surface normal half a corridor
    outside it, ``into`` normal to the edge and that normal, on the side of ``spec.into_opening``."""
    ends = surface.closest(np.array([spec.start_mm, spec.end_mm], float)).points_mm
    along = ends[1] - ends[0]
    length = float(np.linalg.norm(along))
    along /= length
    origin = ends.mean(axis=0)
    hint = np.asarray(spec.into_opening, float)
    hint = hint - (hint @ along) * along
    hint /= np.linalg.norm(hint)
    normal = surface.closest((origin - 0.5 * spec.corridor_mm * hint)[None]).normals[0]
    into = np.cross(normal, along)
    into = into if into @ hint > 0 else -into
    return EdgeFrame(origin, along, into, normal, 0.5 * length)


def _trimmed_line(x: np.ndarray, y: np.ndarray, rounds: int = 3) -> tuple[float, float]:
    """(intercept, slope) of y on x by least squares, thrice dropping residuals beyond 3 robust sigmas."""
    keep = np.ones(len(x), bool)
    c = np.zeros(2)
    for _ in range(rounds):
        if keep.sum() < 3:
            break
        c = np.polyfit(x[keep], y[keep], 1)[::-1]
        r = y - (c[0] + c[1] * x)
        sigma = 1.4826 * np.median(np.abs(r[keep])) + 1e-9
        keep = np.abs(r) <= 3.0 * sigma
    return float(c[0]), float(c[1])


def edge_position(coords: np.ndarray, corridor_mm: float) -> tuple[float, np.ndarray] | None:
    """Where the surface ends along ``into`` (mm) from points in :meth:`EdgeFrame.coordinates`: a line fitted
    to the surface outside the edge (``into`` < -2 mm), the depth the points drop to inside it, and a line
    fitted to the wall between a quarter and three quarters of that depth below the surface, taken where it
    meets the surface. Returns (position, mask of the wall points) or None when the points show no wall."""
    s, h = coords[:, 1], coords[:, 2]
    outside = (s < -2.0) & (s >= -corridor_mm)
    if outside.sum() < 10:
        return None
    a0, a1 = _trimmed_line(s[outside], h[outside])
    r = h - (a0 + a1 * s)  # height above the surface outside the edge, continued
    inside = s > 0
    if inside.sum() < 10:
        return None
    depth = -float(np.percentile(r[inside], 5))
    if depth < 1.0:
        return None
    wall = (r < -0.25 * depth) & (r > -0.75 * depth) & (s > -corridor_mm) & (s < corridor_mm)
    if wall.sum() < 10:
        return None
    c0, _ = _trimmed_line(r[wall], s[wall])
    return c0, wall


def sample_surface(vertices_mm: np.ndarray, triangles: np.ndarray, per_mm2: float, seed: int = 1) -> np.ndarray:
    """Points spread uniformly over the triangles (frame of ``vertices_mm``, mm), ``per_mm2`` on average:
    each triangle picked in proportion to its area, a uniform barycentric point on it."""
    v = np.asarray(vertices_mm, float)[np.asarray(triangles)]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    rng = np.random.default_rng(seed)
    n = int(max(1, round(per_mm2 * area.sum())))
    pick = rng.choice(len(v), n, p=area / area.sum())
    a, b = rng.random((2, n))
    flip = a + b > 1.0
    a[flip], b[flip] = 1.0 - a[flip], 1.0 - b[flip]
    t = v[pick]
    return t[:, 0] + a[:, None] * (t[:, 1] - t[:, 0]) + b[:, None] * (t[:, 2] - t[:, 0])


def _cad_samples_near(surface: CadSurface, frame: EdgeFrame, corridor_mm: float) -> np.ndarray:
    """Points sampled evenly on the CAD triangles within the edge's corridor (frame F, mm)."""
    v = np.asarray(surface.mesh.vertices, float)
    t = np.asarray(surface.mesh.triangles)
    c = frame.coordinates(v[t].mean(axis=1))
    near = (np.abs(c[:, 0]) <= frame.half_length_mm + corridor_mm) & (np.abs(c[:, 1]) <= 2 * corridor_mm) & (
        np.abs(c[:, 2]) <= 2 * corridor_mm)
    if not near.any():
        raise InspectionError("no CAD triangle near the edge")
    return sample_surface(v, t[near], CAD_SAMPLES_PER_MM2)


def edge(spec: EdgeSpec, template: InspectionTemplate, cloud: MeasuredCloud,
         rule: DecisionRule) -> CharacteristicResult:
    """Trimmed-edge / opening position: the edge found in the cloud minus the one found the same way on the
    CAD (:func:`edge_position`), normal to the edge in the surface; + = material beyond the CAD edge. The
    points within a corridor of the edge's ends (where the walls of a corner meet) are left out."""
    method = "edge of the surface fitted outside it and along its wall, against the CAD's found alike"
    frame = edge_frame(spec, cloud.surface)
    half = frame.taken_half_mm(spec.corridor_mm)
    c = frame.coordinates(cloud.points_mm)
    near = np.flatnonzero(np.all(np.abs(c) <= half, axis=1))
    cad = frame.coordinates(_cad_samples_near(cloud.surface, frame, spec.corridor_mm))
    cad = cad[np.all(np.abs(cad[:, :2]) <= half[:2], axis=1)]
    nominal = edge_position(cad, spec.corridor_mm)
    if nominal is None:
        raise InspectionError(f"{spec.id}: the CAD shows no edge with a wall at {spec.start_mm}-{spec.end_mm}")
    found = edge_position(c[near], spec.corridor_mm) if len(near) >= MIN_POINTS else None
    if found is None:
        return _not_measured(spec, "edge", method, len(near), "the cloud shows no edge with a wall there")
    actual = found[0] - nominal[0]
    wall_ids = near[found[1]]
    u = float(np.median(cloud.uncertainty_mm[wall_ids]))
    status, reason = _decided(spec, actual, u, rule)
    at = frame.origin + nominal[0] * frame.into
    return CharacteristicResult(spec.id, spec.name, "edge", method, actual, spec.lower_mm, spec.upper_mm, u, status,
                                reason, len(wall_ids), actual, actual, tuple(map(float, at)), near,
                                c[near, 1] - nominal[0], direction=tuple(map(float, frame.into)))


EVALUATORS = {"surface_profile": surface_profile, "flatness": flatness, "section": section, "edge": edge}


def evaluate(template: InspectionTemplate, cloud: MeasuredCloud, rule: DecisionRule,
             rows: Sequence[slice] | None = None) -> tuple[CharacteristicResult, ...]:
    """Every characteristic of ``template`` on ``cloud`` (frame F), in the template's order; a characteristic that
    takes the part's general tolerance must have been given it (``InspectionTemplate.with_general_tolerance``).
    ``rows``: the rows of ``cloud`` each characteristic is evaluated on, in the template's order (the points of its
    region, ``region_points``; its ``point_ids`` index ``cloud`` all the same); None: all of them for each."""
    if template.needs_general_tolerance:
        raise InspectionError(f"characteristics {', '.join(template.needs_general_tolerance)} of "
                              f"{template.part_number} take the general tolerance, which was not given")
    if rows is None:
        out = tuple(EVALUATORS[spec.kind](spec, template, cloud, rule) for spec in template.characteristics)
    else:
        out = tuple(replace(r, point_ids=r.point_ids + at.start) for r, at in zip(
            (EVALUATORS[spec.kind](spec, template, cloud.rows(at), rule)
             for spec, at in zip(template.characteristics, rows, strict=True)), rows, strict=True))
    log.info("characteristics of %s: %s", template.part_number,
             ", ".join(f"{r.id} {r.status}" for r in out))
    return out
