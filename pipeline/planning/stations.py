"""Measurement-AGV stations along the part's floor contour (paper Eq. 13-14), and the floor they may use.

The part mesh (frame F, mm, floor z = 0) is projected onto the floor; the union of its triangles' shadows,
holes filled, is the contour. Stations sit on the outward offset of the contour at distance
``D in (d3 + w/2, d4 + w/2)`` (Eq. 13), spaced evenly with ``step in (p, p + m)`` (Eq. 14), where ``m`` is the
width of one scan footprint less the overlap; each station heads along the contour (counter-clockwise, the
part on the chassis' left) so that the arm works across the chassis towards the part.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
import open3d as o3d
import shapely
from shapely.geometry import LinearRing, Point, Polygon, box
from shapely.ops import unary_union
from tandemscan.pipeline.planning.parameters import ScanFootprint, StationSpacing

log = logging.getLogger(__name__)


class StationPlanningError(ValueError):
    """No valid measurement-AGV stations (empty mesh, inconsistent distances, no free floor)."""


@dataclass(frozen=True)
class AgvStation:
    """A measurement-AGV station in F: centre (mm), heading (rad), where it is along the contour (mm)."""

    index: int
    x_mm: float
    y_mm: float
    heading_rad: float
    arc_mm: float

    @property
    def xy(self) -> np.ndarray:
        return np.array([self.x_mm, self.y_mm])

    @property
    def tangent(self) -> np.ndarray:
        """Unit direction of travel along the contour (counter-clockwise)."""
        return np.array([math.cos(self.heading_rad), math.sin(self.heading_rad)])

    @property
    def towards_part(self) -> np.ndarray:
        """Unit horizontal direction from the station to the part: the tangent turned left."""
        t = self.tangent
        return np.array([-t[1], t[0]])


@dataclass(frozen=True)
class StationLayout:
    """The stations and the geometry they came from; ``skipped`` are (arc mm, reason) of dropped places."""

    contour: Polygon
    path: Polygon
    distance_mm: float
    step_mm: float
    stations: tuple[AgvStation, ...]
    skipped: tuple[tuple[float, str], ...]


def floor_contour(mesh: o3d.geometry.TriangleMesh) -> Polygon:
    """The part's shadow on the floor (F xy, mm), holes filled.

    For a closed mesh the shadow is the union of the shadows of its upward-facing triangles; its outline is
    made of the projected boundary edges of the upward-facing region, which are noded and polygonized. This
    stays fast for meshes of many triangles.
    """
    v = np.asarray(mesh.vertices)
    tri = np.asarray(mesh.triangles)
    if len(tri) == 0:
        raise StationPlanningError("the part mesh has no triangles")
    p = v[tri]
    nz = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (p[:, 1, 1] - p[:, 0, 1]) * (p[:, 2, 0] - p[:, 0, 0])
    scale = float(np.abs(nz).max())
    faces_up = tri[nz > 1e-9 * scale]
    faces_down = tri[nz < -1e-9 * scale]
    if len(faces_up) < len(faces_down):  # inward winding: the other side casts the same shadow
        faces_up = faces_down
    if len(faces_up) == 0:
        raise StationPlanningError("the part mesh casts no shadow on the floor")
    edges = np.sort(np.concatenate([faces_up[:, [0, 1]], faces_up[:, [1, 2]], faces_up[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    boundary = v[uniq[counts == 1]][:, :, :2]
    lines = shapely.multilinestrings(boundary)
    faces = list(shapely.polygonize([shapely.union_all(lines)]).geoms)
    if not faces:
        raise StationPlanningError("the part's floor outline does not close")
    shadow = unary_union(faces).buffer(0.5).buffer(-0.5)  # close slivers between neighbouring faces
    if shadow.geom_type == "MultiPolygon":
        shadow = max(shadow.geoms, key=lambda g: g.area)
        log.warning("part shadow falls apart on the floor; planning around its largest piece")
    return Polygon(shadow.exterior)


def free_floor(spacing: StationSpacing) -> Polygon:
    """Floor a chassis may stand on: the cell rectangle less the keep-out zones (F xy, mm)."""
    x0, y0, x1, y1 = spacing.floor_xy_mm
    floor = box(x0, y0, x1, y1)
    for zone in spacing.keep_out_xy_mm:
        floor = floor.difference(Polygon(zone))
    return floor


def standoff_mm(spacing: StationSpacing) -> float:
    """Centre distance of the stations from the contour: the middle of ``(d3 + w/2, d4 + w/2)`` (Eq. 13), mm."""
    d3, d4, w = spacing.arm_standoff_min_mm, spacing.arm_standoff_max_mm, spacing.agv_width_mm
    if d4 <= d3:
        raise StationPlanningError(f"arm standoff: d4 = {d4} mm must exceed d3 = {d3} mm")
    return 0.5 * (d3 + d4) + 0.5 * w


def station_count(length_mm: float, p_mm: float, m_mm: float) -> int:
    """Stations on a closed path of ``length_mm`` so that the step ``length/N`` lies in ``(p, p + m)`` (Eq. 14).

    The fewest such N; when no integer N fits (a path shorter than ``p``, or ``m`` too small for the
    length) the count that makes the step nearest the interval is used and a warning is logged.
    """
    if length_mm <= 0:
        raise StationPlanningError("the station path has no length")
    n_lo = math.floor(length_mm / (p_mm + m_mm)) + 1  # smallest N with L/N < p + m
    n_hi = math.ceil(length_mm / p_mm) - 1  # largest N with L/N > p
    if n_lo <= n_hi:
        return max(n_lo, 1)
    log.warning("no station count gives a step in (%.0f, %.0f) mm on a %.0f mm path", p_mm, p_mm + m_mm, length_mm)
    return max(n_lo, 1)


def place_stations(mesh: o3d.geometry.TriangleMesh, spacing: StationSpacing, footprint: ScanFootprint) -> StationLayout:
    """Stations around the part (Eq. 13-14), at most one scan's useful width (``footprint.width_mm``) more than
    the least step apart; places in keep-out zones or off the floor are skipped, with reason."""
    contour = floor_contour(mesh)
    distance = standoff_mm(spacing)
    path = Polygon(contour.buffer(distance, quad_segs=16).exterior)
    ring = LinearRing(path.exterior.coords)
    if not ring.is_ccw:
        ring = LinearRing(list(ring.coords)[::-1])
    length = ring.length
    n = station_count(length, spacing.station_step_mm, footprint.width_mm)
    step = length / n
    floor = free_floor(spacing)
    half = 0.5 * spacing.agv_width_mm
    stations, skipped = [], []
    for k in range(n):
        s = k * step
        p = ring.interpolate(s)
        a, b = ring.interpolate(s - 1.0 if s >= 1.0 else s + length - 1.0), ring.interpolate((s + 1.0) % length)
        heading = math.atan2(b.y - a.y, b.x - a.x)
        footprint = Point(p.x, p.y).buffer(half, quad_segs=8)
        if not floor.contains(footprint):
            skipped.append((s, "chassis footprint in a keep-out zone or off the cell floor"))
            continue
        stations.append(AgvStation(len(stations), p.x, p.y, heading, s))
    if not stations:
        raise StationPlanningError("no measurement-AGV station fits on the free floor around the part")
    for s, why in skipped:
        log.info("station at %.0f mm along the path skipped: %s", s, why)
    return StationLayout(contour, Polygon(ring), distance, step, tuple(stations), tuple(skipped))


def offset_ring(contour: Polygon, distance_mm: float, spacing_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every ``spacing_mm`` on the contour's outward offset by ``distance_mm``, and unit vectors inward."""
    ring = LinearRing(contour.buffer(distance_mm, quad_segs=16).exterior.coords)
    if not ring.is_ccw:
        ring = LinearRing(list(ring.coords)[::-1])
    count = max(int(math.ceil(ring.length / spacing_mm)), 3)
    s = np.arange(count) * ring.length / count
    pts = np.array([[ring.interpolate(t).x, ring.interpolate(t).y] for t in s])
    ahead = np.array([[ring.interpolate((t + 1.0) % ring.length).x, ring.interpolate((t + 1.0) % ring.length).y]
                      for t in s])
    tangent = ahead - pts
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    inward = np.c_[-tangent[:, 1], tangent[:, 0]]  # counter-clockwise ring: the inside is on the left
    return pts, inward
