"""The points of a tiled cloud in small regions at full density (docs/compute.md, "Tiles"): what a template's
characteristics are evaluated on and the deviation areas' close-ups drawn from where the cloud is inspected tile by tile
and the process that writes the report holds only an even sample of it.

A :class:`Region` (frame F, mm) is an intersection of slabs, optionally on some CAD triangles:
:func:`characteristic_region` bounds what a characteristic selects (its patch's box and face groups, a section's slab,
an edge's corridor in the edge's frame; ``characteristics``: the evaluator selects again among them),
:func:`closeup_region` the square of an area's close-up (``characteristic_figures.closeup``). A :class:`RegionTile`
unit reads its tile's deviations (``tile_inspection.inspect_tile``: points, deviations, closest CAD triangles and U)
and returns each region's points in the tile's order; joined in the tiles' order they are the untiled cloud's points
there in its order, so a characteristic evaluated on them is the one evaluated on the untiled cloud.

Bounded: all the regions together gather at most :data:`REGION_POINTS` points, counted on the report's even sample
(:func:`budgeted`); a region that would take more than its share is thinned evenly (every k-th of its points in each
tile) and the characteristic evaluated on it says so.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from tandemscan.config.inspection_template import InspectionTemplate, PatchSpec
from tandemscan.pipeline.compute import ComputeBackend
from tandemscan.pipeline.geometry.frames import transform_points
from tandemscan.pipeline.inspection.characteristics import MeasuredCloud, edge_frame
from tandemscan.pipeline.inspection.deviation_areas import DeviationArea
from tandemscan.pipeline.inspection.inspect import CadSurface, InspectionError, in_chunks
from tandemscan.pipeline.stitching.tiles import TileCloud

#: the most points all of a report's regions gather together (48 B each: about 50 MB in the process that writes the
#: report, as its sample of ``[compute] report_points``)
REGION_POINTS = 1_000_000
#: a region reaches this far (mm) beyond the slabs it bounds: a superset of what its characteristic selects, whatever
#: the rounding of a point's coordinate along a slab's axis
MARGIN_MM = 1e-3
CLOSEUP_MIN_RADIUS_MM = 40.0  # a close-up shows at least this far around an area's centroid


@dataclass(frozen=True)
class Region:
    """Points of frame F (mm) within ``half_mm[j]`` (inf: unbounded) of ``centres_mm[j]`` along each unit vector
    ``axes[j]`` (widened by :data:`MARGIN_MM`) and, where ``triangles`` names some (sorted CAD triangle ids), whose
    closest CAD triangle is one of them; ``step``: every ``step``-th of them in a tile is taken (:func:`budgeted`)."""

    axes: np.ndarray
    centres_mm: np.ndarray
    half_mm: np.ndarray
    triangles: np.ndarray | None = None
    step: int = 1

    @classmethod
    def box(cls, min_mm, max_mm) -> Region:
        """The axis-aligned box from ``min_mm`` to ``max_mm`` (F, mm; bounds inclusive)."""
        lo, hi = np.asarray(min_mm, float), np.asarray(max_mm, float)
        return cls(np.eye(3), 0.5 * (lo + hi), 0.5 * (hi - lo))

    def intersection(self, other: Region) -> Region:
        """The points in this region and in ``other`` (its slabs added; the triangles of both)."""
        tri = self.triangles if other.triangles is None else other.triangles if self.triangles is None else (
            np.intersect1d(self.triangles, other.triangles))
        return Region(np.vstack([self.axes, other.axes]), np.r_[self.centres_mm, other.centres_mm],
                      np.r_[self.half_mm, other.half_mm], tri, self.step)

    def mask(self, points_F_mm: np.ndarray, triangle_ids: np.ndarray | None) -> np.ndarray:
        """(N,) bool: the points (F, mm) in the region, with their closest CAD triangles (None: not known, for a
        region that names none)."""
        inside = np.ones(len(points_F_mm), bool)
        for axis, centre, half in zip(self.axes, self.centres_mm, self.half_mm, strict=True):
            if math.isfinite(half):
                inside &= np.abs(points_F_mm @ axis - centre) <= half + MARGIN_MM
        if self.triangles is not None:
            if triangle_ids is None:
                raise ValueError("a region on CAD triangles needs the points' closest triangles")
            inside &= np.isin(triangle_ids, self.triangles)
        return inside

    def digest(self, h) -> None:
        """Feed what the region selects into the hash ``h``."""
        for a in (self.axes, self.centres_mm, self.half_mm, np.array([self.step], float)):
            h.update(np.ascontiguousarray(a, np.float64).tobytes())
        if self.triangles is not None:
            h.update(np.ascontiguousarray(self.triangles, np.int64).tobytes())


UNBOUNDED = Region(np.zeros((0, 3)), np.zeros(0), np.zeros(0))


def patch_region(patch: PatchSpec, surface: CadSurface) -> Region:
    """The region of a template's patch (``characteristics.patch_mask``): its box and, where it names face groups,
    the CAD triangles of those groups."""
    region = UNBOUNDED if patch.min_mm is None else Region.box(patch.min_mm, patch.max_mm)
    if not patch.face_groups:
        return region
    groups = np.asarray(surface.mesh.triangle_material_ids)
    if len(groups) != len(surface.mesh.triangles):
        raise InspectionError("the template selects face groups but the CAD mesh has none")
    return replace(region, triangles=np.flatnonzero(np.isin(groups, patch.face_groups)))


def characteristic_region(spec, template: InspectionTemplate, surface: CadSurface) -> Region:
    """Where the characteristic ``spec`` of ``template`` takes its points (F, mm; a superset of what
    ``characteristics`` selects): a profile's or a flatness's patch; a section's slab of its plane, as wide as its
    half width or the smoothing radius, in its patch where it names one; an edge's corridor in the edge's frame."""
    if spec.kind in ("surface_profile", "flatness"):
        return patch_region(template.region(spec.region), surface)
    if spec.kind == "section":
        n = np.asarray(spec.normal, float) / np.linalg.norm(spec.normal)
        slab = Region(n[None], np.array([n @ np.asarray(spec.point_mm, float)]),
                      np.array([max(spec.half_width_mm, template.smoothing_mm)]))
        return slab if spec.region is None else slab.intersection(patch_region(template.region(spec.region), surface))
    if spec.kind == "edge":
        frame = edge_frame(spec, surface)
        axes = np.array([frame.along, frame.into, frame.normal])
        return Region(axes, axes @ frame.origin, frame.taken_half_mm(spec.corridor_mm))
    raise InspectionError(f"{spec.id}: no region for a characteristic of kind {spec.kind!r}")


def closeup_radius_mm(area: DeviationArea) -> float:
    """Half the side of the square an area's close-up shows (mm): three equivalent radii of the area, at least
    :data:`CLOSEUP_MIN_RADIUS_MM`."""
    return max(3.0 * math.sqrt(area.area_mm2 / math.pi), CLOSEUP_MIN_RADIUS_MM)


def closeup_region(area: DeviationArea) -> Region:
    """The box around the ball an area's close-up draws its points from (``characteristic_figures.closeup``)."""
    reach = closeup_radius_mm(area) * math.sqrt(2.0)
    centre = np.asarray(area.centroid_mm, float)
    return Region.box(centre - reach, centre + reach)


def budgeted(regions: Sequence[Region], sample_F_mm: np.ndarray, triangle_ids: np.ndarray | None,
             points_per_sample_point: float, budget: int) -> tuple[Region, ...]:
    """``regions`` each with the step that keeps all of them together within ``budget`` points
    (:data:`REGION_POINTS` in the product): a region's points counted on the report's even sample (``sample_F_mm``,
    F, mm, with its closest CAD triangles; None where no region names triangles) times ``points_per_sample_point``;
    those under an equal share of what the smaller ones leave are taken whole, the others thinned to that share."""
    counts = [float(np.count_nonzero(r.mask(sample_F_mm, triangle_ids))) * points_per_sample_point
              for r in regions]
    share, left = math.inf, float(budget)
    for k, n in enumerate(sorted(counts)):
        fair = left / (len(counts) - k)
        if n > fair:
            share = fair
            break
        left -= n
    return tuple(replace(r, step=max(1, math.ceil(n / share))) for r, n in zip(regions, counts, strict=True))


@dataclass(frozen=True)
class RegionPoints:
    """A region's points of the cloud (F, mm), in the cloud's order: their signed deviations from the CAD (mm), closest
    CAD triangles and expanded uncertainty U (mm; 0 where the tiles were inspected without it); ``step``: every
    ``step``-th of the region's points (1: all)."""

    points_mm: np.ndarray
    deviations_mm: np.ndarray
    triangle_ids: np.ndarray
    uncertainty_mm: np.ndarray
    step: int = 1

    @classmethod
    def joined(cls, parts: Sequence[RegionPoints], step: int) -> RegionPoints:
        """The parts one after the other (the tiles' in the cloud's order)."""
        return cls(*(np.concatenate([getattr(p, name) for p in parts]) if parts else empty for name, empty in (
            ("points_mm", np.zeros((0, 3))), ("deviations_mm", np.zeros(0)), ("triangle_ids", np.zeros(0, np.int64)),
            ("uncertainty_mm", np.zeros(0)))), step)

    def __len__(self) -> int:
        return len(self.deviations_mm)

    def measured(self, surface: CadSurface) -> MeasuredCloud:
        """The points as the characteristics take them, against ``surface``."""
        return MeasuredCloud(self.points_mm, self.deviations_mm, self.triangle_ids, self.uncertainty_mm, surface)


@dataclass(frozen=True)
class RegionTile:
    """One unit of the gathering: the tile whose deviations lie in ``file`` (relative to the scan store ``store``,
    ``tile_inspection.inspect_tile``) and the ``regions`` whose points it returns."""

    file: str
    store: str
    regions: tuple[Region, ...]

    def key(self) -> str:
        """The unit's name: everything its points depend on."""
        h = hashlib.blake2b(digest_size=16)
        h.update(self.file.encode())
        for r in self.regions:
            r.digest(h)
        return f"region-tile-{h.hexdigest()}"


def tile_region_points(unit: RegionTile) -> tuple[RegionPoints, ...]:
    """Each region's points in the unit's tile (every ``step``-th of them), in the tile's order."""
    with np.load(Path(unit.store) / unit.file) as data:
        points, triangles = data["points_F"], data["triangle_ids"]
        picked = [np.flatnonzero(r.mask(points, triangles))[:: r.step] for r in unit.regions]
        if not any(len(ids) for ids in picked):
            return tuple(RegionPoints.joined((), r.step) for r in unit.regions)
        d = data["deviation_mm"]
        u = data["uncertainty_mm"] if "uncertainty_mm" in data.files else np.zeros(len(d))
    return tuple(RegionPoints(points[ids], d[ids], triangles[ids], u[ids], r.step)
                 for r, ids in zip(unit.regions, picked, strict=True))


def gather(files: Sequence[str], store: str | Path, regions: Sequence[Region], backend: ComputeBackend
           ) -> tuple[RegionPoints, ...]:
    """Each region's points in the tiles' deviations ``files`` (in the cloud's order) by :func:`tile_region_points`
    on ``backend``, joined in that order."""
    if not regions:
        return ()
    units = [RegionTile(f, str(store), tuple(regions)) for f in files]
    found = backend.map(tile_region_points, units, [u.key() for u in units])
    return tuple(RegionPoints.joined([f[i] for f in found], r.step) for i, r in enumerate(regions))


@dataclass(frozen=True)
class PlacedTile:
    """One unit of the gathering from a tile's cloud before its inspection: the tile ``tile`` of the merged cloud in
    the scan store ``store`` (W, mm) placed in F by ``T_F_W`` (4x4, mm), and the ``regions`` (F, none on CAD
    triangles) whose points it returns."""

    tile: TileCloud
    store: str
    T_F_W: np.ndarray
    regions: tuple[Region, ...]

    def key(self) -> str:
        """The unit's name: everything its points depend on."""
        h = hashlib.blake2b(digest_size=16)
        h.update(self.tile.file.encode())
        h.update(np.ascontiguousarray(self.T_F_W, np.float64).tobytes())
        for r in self.regions:
            r.digest(h)
        return f"placed-tile-{self.tile.index:05d}-{h.hexdigest()}"


def placed_tile_points(unit: PlacedTile) -> np.ndarray:
    """The unit's tile's points (W, mm) that lie, placed in F, in any of its regions (every ``step``-th of a region's),
    in the tile's order."""
    with np.load(Path(unit.store) / unit.tile.file) as data:
        points_W = data["points"]  # its normals and counts stay on disk
    placed = in_chunks(transform_points, np.asarray(unit.T_F_W, float), points_W)
    keep = np.zeros(len(points_W), bool)
    for r in unit.regions:
        keep[np.flatnonzero(r.mask(placed, None))[:: r.step]] = True
    return points_W[keep]


def gather_placed(tiles: Sequence[TileCloud], store: str | Path, T_F_W: np.ndarray, regions: Sequence[Region],
                  backend: ComputeBackend) -> np.ndarray:
    """The cloud's points (W, mm; its ``tiles`` in the scan store ``store``, in its order) that lie, placed in F by
    ``T_F_W``, in any of ``regions``: :func:`placed_tile_points` of every tile on ``backend``."""
    units = [PlacedTile(t, str(store), np.asarray(T_F_W, float), tuple(regions)) for t in tiles]
    found = backend.map(placed_tile_points, units, [u.key() for u in units])
    return np.concatenate([np.zeros((0, 3)), *found])
