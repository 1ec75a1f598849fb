"""The deviation of a job's cloud from the CAD, tile by tile (docs/compute.md, "Tiles"): memory bounded by the tile.

Once the cloud is aligned to the CAD (``T_F_W``, from a bounded subsample of it: ``tiles.every_kth``), each point's
signed deviation depends only on the point and the CAD surface (``inspect.CadSurface.closest``, point by point), so
each tile of the merged cloud (``tiles.merge_tiles``) is inspected on its own: an :class:`InspectTile` unit reads its
tile's cloud, places it in F, writes its points, normals and deviations beside the tile (read back by
:func:`write_deviation_ply`, streamed) and returns a :class:`TileDeviations` summary: count,
mean and sum of squared differences (combined exactly as Chan et al.'s parallel variance), sum of squares,
extremes, the points below and above the tolerance band, and a histogram of fixed bins. The report's figures come
from those summaries (:func:`deviation_figures`): count, mean, sigma, RMS, extremes and the tolerance shares to the
rounding of their sums, the 5th and 95th percentiles exactly (a second pass reads back only the deviations in the
histogram bins that hold those ranks). Equal to the untiled ``inspect.DeviationStats`` and ``ToleranceResult`` to
1e-9 mm.

The deviation areas from every point (:func:`tile_areas`): an :class:`AreaTile` unit a tile reads its deviations and
its neighbours' within a halo (:data:`HALO_SMOOTHINGS`), links its own points beyond the band and returns their
sums (``deviation_areas.AreaPiece``) with its linked points near its x ends (:class:`TileAreas`); the pieces are
joined across the tiles in the process that writes the report (:func:`joined_areas`). Equal to the untiled
``deviation_areas.find_deviation_areas`` to 1e-9, but for the link distance where three point spacings come within
0.03 mm of the smoothing radius or beyond it: the tiles then link at three times a bound of the spacing (its median
to the 0.01 mm above), up to 0.03 mm farther than the untiled cloud (:func:`tile_areas`).

A job's inspection of a tiled cloud (:class:`TiledInspection`, docs/compute.md "Tiles"): the alignment, the points'
uncertainty U and the maps are those of an even sample of the cloud in the process that writes the report
(``[compute] report_points``); the deviation figures of the whole cloud (count, mean, sigma, RMS, extremes,
percentiles, tolerance shares) and its deviation areas come from every point, tile by tile, and so does
``cloud_deviation.ply``, each point with the U of the sample's nearest point (:class:`UncertaintyField`); the
template's characteristics and the areas' close-ups from every point in their regions
(:meth:`InspectedTiles.points_in`, ``region_points``).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from tandemscan.pipeline.compute import ComputeBackend, trim_heap
from tandemscan.pipeline.geometry.frames import invert, rotate_vectors, transform_points
from tandemscan.pipeline.inspection.alignment import in_balls
from tandemscan.pipeline.inspection.deviation_areas import (
    THIN_ABOVE_POINTS,
    AreaPiece,
    DeviationArea,
    DeviationCloud,
    areas_of,
    link_distance,
    linked_pieces,
    local_deviations,
)
from tandemscan.pipeline.inspection.inspect import CadSurface, DeviationStats, ToleranceResult, in_chunks
from tandemscan.pipeline.inspection.region_points import Region, RegionPoints, gather, gather_placed
from tandemscan.pipeline.io import npz_blocks
from tandemscan.pipeline.io.durable import write_durably
from tandemscan.pipeline.io.export import PlyChunk, write_ply_streamed
from tandemscan.pipeline.io.npz_blocks import row_blocks
from tandemscan.pipeline.stitching.tiles import TILES_FOLDER, TileCloud, TilePoints, read_tile

#: the edges (mm) of the deviation histogram each tile returns (0.01 mm bins over +-20 mm, and one bin beyond each
#: end): only a bin's count travels, the percentiles are found exactly from its values (:func:`deviation_figures`)
HISTOGRAM_EDGES_MM = np.linspace(-20.0, 20.0, 4001)


@dataclass(frozen=True)
class InspectTile:
    """One unit of the tiled inspection: the tile ``tile`` of the merged cloud in the scan store ``store``, placed
    in the CAD frame F by ``T_F_W`` (4x4, mm) and compared with the CAD in ``mesh_file`` (F, mm: a ``.npz`` of the
    job's CAD as it took it, :func:`write_cad`; its triangles ``reversed`` wound the other way: ``CadSurface``), the
    tolerance band ``[lower_mm, upper_mm]``; ``sample``: what the tile takes from the
    inspection of the report's sample (:class:`FromSample`; None: nothing)."""

    tile: TileCloud
    store: str
    mesh_file: str
    T_F_W: np.ndarray
    lower_mm: float
    upper_mm: float
    reversed: np.ndarray | None = None
    sample: FromSample | None = None

    def key(self) -> str:
        """The unit's name: everything its deviations depend on."""
        h = hashlib.blake2b(digest_size=16)
        for text in (self.tile.file, self.mesh_file):
            h.update(text.encode())
        if self.sample is not None:
            h.update(self.sample.uncertainty.encode())
            h.update(np.array(self.sample.left_out, np.float64).tobytes())
        h.update(np.ascontiguousarray(self.T_F_W, np.float64).tobytes())
        h.update(np.array([self.lower_mm, self.upper_mm], np.float64).tobytes())
        if self.reversed is not None:
            h.update(np.packbits(np.asarray(self.reversed, bool)).tobytes())
        return f"inspect-tile-{self.tile.index:05d}-{h.hexdigest()}"

    def deviations_file(self) -> str:
        """Where the unit writes its tile's deviations (relative to the scan store): beside the tile, named by its
        key."""
        return f"{Path(self.tile.file).parent.as_posix()}/{self.key()}.npz"


@dataclass(frozen=True)
class FromSample:
    """What a tile's inspection takes from the inspection of the report's sample (module doc): ``uncertainty``, the
    file of an :class:`UncertaintyField` in the scan store whose nearest point's U each point takes ("": none), and
    ``left_out``, balls (x, y, z, radius; W, mm) whose points are no part surface and are left out, as the sample's
    were (``alignment.sphere_balls``: the reference spheres)."""

    uncertainty: str = ""
    left_out: tuple[tuple[float, float, float, float], ...] = ()


@dataclass(frozen=True)
class TileDeviations:
    """A tile's inspection: its deviations' file (relative to the scan store: points and unit normals in F, mm,
    float64, signed deviations ``deviation_mm``, + along the CAD's outward normal, closest CAD triangles
    ``triangle_ids``) and their summary (mm, mm^2)."""

    index: int
    file: str
    count: int
    mean_mm: float
    m2_mm2: float  # sum of the squared differences from the mean
    sum_sq_mm2: float
    min_mm: float
    max_mm: float
    below: int
    above: int
    histogram: np.ndarray  # counts in the bins of HISTOGRAM_EDGES_MM, one bin below and one above them
    x_min_mm: float  # the extent of its points' x in W (mm; inf, -inf without points): where its halo reaches
    x_max_mm: float


@functools.lru_cache(maxsize=2)
def _surface(mesh_file: str, reversed_bits: bytes | None, triangles: int) -> CadSurface:
    """The CAD surface of ``mesh_file`` (the job's CAD as it took it, :func:`write_cad`), built once a worker process
    (the units of a job share it)."""
    reversed = None if reversed_bits is None else np.unpackbits(
        np.frombuffer(reversed_bits, np.uint8), count=triangles).astype(bool)
    with np.load(mesh_file) as data:
        mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(data["vertices_mm"]),
                                         o3d.utility.Vector3iVector(data["triangles"]))
    return CadSurface(mesh, reversed)


def _bins(deviations_mm: np.ndarray) -> np.ndarray:
    """The histogram bin of each deviation (0: below the first edge, len(edges): from the last one on)."""
    return np.searchsorted(HISTOGRAM_EDGES_MM, deviations_mm, side="right")


def inspect_tile(unit: InspectTile) -> TileDeviations:
    """The deviations of the unit's tile from the CAD (with each point's U where the unit names a field), written to
    ``<store>/tiles/<unit key>.npz``, and their summary."""
    cloud = read_tile(unit.store, unit.tile)
    sample = unit.sample or FromSample()
    if sample.left_out:
        keep = ~in_balls(cloud.points_mm, (((x, y, z), radius) for x, y, z, radius in sample.left_out))
        cloud = TilePoints(cloud.points_mm[keep], cloud.normals[keep], None)
    reversed = unit.reversed
    surface = _surface(unit.mesh_file, None if reversed is None else np.packbits(reversed).tobytes(),
                       0 if reversed is None else len(reversed))
    T = np.asarray(unit.T_F_W, float)
    points_F = in_chunks(transform_points, T, cloud.points_mm)
    normals_F = in_chunks(rotate_vectors, T, cloud.normals)
    closest = surface.closest(points_F) if len(points_F) else None
    d, triangles = (np.empty(0), np.empty(0, np.int64)) if closest is None else (closest.signed_mm,
                                                                                 closest.triangle_ids)
    file = unit.deviations_file()
    u = {} if not sample.uncertainty else {
        "uncertainty_mm": _field(str(Path(unit.store) / sample.uncertainty)).at(points_F)}
    write_durably(Path(unit.store) / file, functools.partial(
        np.savez, points_F=points_F, normals_F=normals_F, deviation_mm=d, triangle_ids=triangles, **u))
    n = len(d)
    mean = float(d.mean()) if n else 0.0
    return TileDeviations(
        unit.tile.index, file, n, mean, float(((d - mean) ** 2).sum()), float((d * d).sum()),
        float(d.min()) if n else math.inf, float(d.max()) if n else -math.inf,
        int(np.count_nonzero(d < unit.lower_mm)), int(np.count_nonzero(d > unit.upper_mm)),
        np.bincount(_bins(d), minlength=len(HISTOGRAM_EDGES_MM) + 1),
        float(cloud.points_mm[:, 0].min()) if n else math.inf, float(cloud.points_mm[:, 0].max()) if n else -math.inf)



def inspect_tiles(tiles: Sequence[TileCloud], store: str | Path, mesh_file: str | Path, T_F_W: np.ndarray,
                  lower_mm: float, upper_mm: float, backend: ComputeBackend,
                  reversed: np.ndarray | None = None, sample: FromSample | None = None
                  ) -> tuple[TileDeviations, ...]:
    """:func:`inspect_tile` of every tile on ``backend``, in the tiles' order (:class:`InspectTile` for the
    arguments; ``mesh_file``: :func:`write_cad`'s). Where a unit fails (or the stage is cut short), the deviations
    the other units wrote are removed: only a stage that returns leaves files for its caller to remove.

    Nine parameters: the tiles, where they and the CAD lie, the placement in F, the band, the CAD's orientation
    and what it takes from the report's sample (the fields of an :class:`InspectTile` unit) and the backend."""
    units = [InspectTile(t, str(store), str(mesh_file), np.asarray(T_F_W, float), lower_mm, upper_mm, reversed,
                         sample) for t in tiles]
    try:
        return tuple(backend.map(inspect_tile, units, [u.key() for u in units]))
    except BaseException:
        for u in units:
            (Path(store) / u.deviations_file()).unlink(missing_ok=True)
        raise


def _read_deviations(store: str | Path, file: str, *names: str) -> list[np.ndarray]:
    with np.load(Path(store) / file) as data:
        return [data[name] for name in names]


def _deviation_chunks(store: str | Path, tiles: Sequence[TileDeviations]) -> Iterator[PlyChunk]:
    """The deviation PLY's vertices (F, mm: points, unit normals, ``deviation_mm`` and, where the tiles have it,
    ``uncertainty_mm``), ``npz_blocks.BLOCK_ROWS`` rows of a tile's file at a time (``npz_blocks.row_blocks``)."""
    for tile in tiles:
        path = Path(store) / tile.file
        with np.load(path) as data:
            scalars = [name for name in ("deviation_mm", "uncertainty_mm") if name in data.files]
        for block in row_blocks(path, ("points_F", "normals_F", *scalars), npz_blocks.BLOCK_ROWS):
            yield PlyChunk(block["points_F"], block["normals_F"], {name: block[name] for name in scalars})


def write_deviation_ply(path: Path, store: str | Path, tiles: Sequence[TileDeviations]) -> Path:
    """The deviation PLY (F, mm: points, unit normals, ``deviation_mm``, with U ``uncertainty_mm`` where the tiles
    were inspected with a field of it) streamed a tile at a time, the vertex count known from the tiles'
    summaries."""
    return write_ply_streamed(path, sum(t.count for t in tiles), _deviation_chunks(store, tiles))


@dataclass(frozen=True)
class DeviationFigures:
    """The report's deviation figures of the whole cloud, from the tiles' summaries."""

    stats: DeviationStats
    tolerance: ToleranceResult


def deviation_figures(store: str | Path, tiles: Sequence[TileDeviations], lower_mm: float, upper_mm: float
                      ) -> DeviationFigures:
    """``inspect.DeviationStats`` and ``ToleranceResult`` of all the tiles' deviations from their summaries (the
    mean and variance combined pairwise, Chan et al.), the percentiles exact by a second pass over the deviations
    in the histogram bins of their ranks."""
    tiles = [t for t in tiles if t.count]
    if not tiles:
        raise ValueError("no deviations to summarise")
    n, mean, m2 = 0, 0.0, 0.0
    for t in tiles:
        total = n + t.count
        delta = t.mean_mm - mean
        mean += delta * t.count / total
        m2 += t.m2_mm2 + delta * delta * n * t.count / total
        n = total
    p5, p95 = _percentiles(store, tiles, n, (5.0, 95.0))
    stats = DeviationStats(n, mean, math.sqrt(m2 / (n - 1)) if n > 1 else 0.0,
                           math.sqrt(sum(t.sum_sq_mm2 for t in tiles) / n), min(t.min_mm for t in tiles),
                           max(t.max_mm for t in tiles), p5, p95)
    above = float(sum(t.above for t in tiles)) * 100.0 / n
    below = float(sum(t.below for t in tiles)) * 100.0 / n
    tolerance = ToleranceResult(lower_mm, upper_mm, 100.0 - above - below, above, below)
    return DeviationFigures(stats, tolerance)


def _percentiles(store: str | Path, tiles: Sequence[TileDeviations], n: int, qs: Sequence[float]) -> list[float]:
    """``np.percentile`` (linear) of all the tiles' deviations at ``qs`` (%): the two order statistics each needs
    found in their histogram bins, whose values alone are read back."""
    cumulative = np.cumsum(sum(t.histogram for t in tiles))
    ranks = {q: q / 100.0 * (n - 1) for q in qs}
    needed = sorted({r for rank in ranks.values() for r in (math.floor(rank), math.ceil(rank))})
    bins = {r: int(np.searchsorted(cumulative, r, side="right")) for r in needed}
    wanted = np.array(sorted(set(bins.values())))
    values: dict[int, list[np.ndarray]] = {int(b): [] for b in wanted}
    for t in tiles:
        if not t.histogram[wanted].any():
            continue
        (d,) = _read_deviations(store, t.file, "deviation_mm")
        of = _bins(d)
        for b in wanted:
            values[int(b)].append(d[of == b])
    in_bin = {b: np.sort(np.concatenate(v)) for b, v in values.items()}
    order = {r: float(in_bin[bins[r]][r - (cumulative[bins[r] - 1] if bins[r] else 0)]) for r in needed}
    out = []
    for q in qs:
        rank = ranks[q]
        lo, hi = order[math.floor(rank)], order[math.ceil(rank)]
        out.append(lo + (hi - lo) * (rank - math.floor(rank)))
    return out


#: a tile's halo reaches this many smoothing radii beyond its points' x (W): each of its points has its neighbours
#: within the smoothing radius and its nearest (the point spacing, the surface share) within three, and so has every
#: screening point within a screening cube's diagonal of it (1.3 radii: ``deviation_areas._screened``), as the
#: untiled cloud has them
HALO_SMOOTHINGS = 3.0
#: the edges (mm) of the nearest-neighbour distances' histogram each tile's areas return (0.01 mm bins): the point
#: spacing the areas are linked by (``deviation_areas.link_distance``) is bounded from it
SPACING_EDGES_MM = np.linspace(0.0, 20.0, 2001)


@dataclass(frozen=True)
class AreaBounds:
    """What the whole cloud's deviation areas are sought by: beyond ``[lower_mm, upper_mm]`` (mm), each point's
    deviation averaged over ``smoothing_mm``, none smaller than ``min_area_mm2`` (``deviation_areas``)."""

    lower_mm: float
    upper_mm: float
    smoothing_mm: float
    min_area_mm2: float


@dataclass(frozen=True)
class AreaTile:
    """One unit of the tiled deviation areas: the tile ``index`` whose deviations lie in ``file`` (relative to the
    scan store ``store``, :func:`inspect_tile`; its points' x in W spanning ``x_mm``), with the deviations' files of
    the tiles its halo reaches before and after it (``before``, ``after``, in the cloud's order); ``T_F_W`` (4x4, mm)
    placed them in F. Its points beyond ``bounds`` are linked within ``link_mm``; ``screen``: the whole cloud's
    areas are screened (``deviation_areas.local_deviations``)."""

    index: int
    file: str
    x_mm: tuple[float, float]
    before: tuple[str, ...]
    after: tuple[str, ...]
    store: str
    T_F_W: np.ndarray
    bounds: AreaBounds
    link_mm: float
    screen: bool

    def key(self) -> str:
        """The unit's name: everything its areas depend on."""
        h = hashlib.blake2b(digest_size=16)
        for text in (self.file, *self.before, "|", *self.after):
            h.update(text.encode())
        b = self.bounds
        h.update(np.array([*self.x_mm, b.lower_mm, b.upper_mm, b.smoothing_mm, self.link_mm, self.screen],
                          np.float64).tobytes())
        h.update(np.ascontiguousarray(self.T_F_W, np.float64).tobytes())
        return f"area-tile-{self.index:05d}-{h.hexdigest()}"


@dataclass(frozen=True)
class TileAreas:
    """A tile's share of the deviation areas (:func:`find_tile_areas`): its points beyond the band linked into
    ``pieces`` (``deviation_areas.AreaPiece``: sums, not points); those of its linked points that lie within the
    link distance of its x ends (F, mm), each with its piece (index into ``pieces``), for the pieces to be joined
    across tiles; and its nearest-neighbour distances' counts in the bins of :data:`SPACING_EDGES_MM` (the last:
    beyond them, the largest ``spacing_max_mm``)."""

    index: int
    pieces: tuple[AreaPiece, ...]
    edge_points_mm: np.ndarray
    edge_pieces: np.ndarray
    spacing_histogram: np.ndarray
    spacing_max_mm: float


def find_tile_areas(unit: AreaTile) -> TileAreas:
    """The unit's tile's pieces of the areas beyond its band, from every one of its points, each averaged over its
    neighbours in the tile and its halo (the points of the tiles before and after it within
    :data:`HALO_SMOOTHINGS` smoothing radii of its x extent in W)."""
    b = unit.bounds
    x_W = invert(np.asarray(unit.T_F_W, float))[0]  # a point of F's x in W: x_W[:3] . p + x_W[3]
    lo, hi = unit.x_mm
    reach = HALO_SMOOTHINGS * b.smoothing_mm

    def halo(file: str) -> tuple[np.ndarray, np.ndarray]:
        p, d = _read_deviations(unit.store, file, "points_F", "deviation_mm")
        x = p @ x_W[:3] + x_W[3]
        keep = (x >= lo - reach) & (x <= hi + reach)
        return p[keep], d[keep]

    own = _read_deviations(unit.store, unit.file, "points_F", "deviation_mm")
    parts = [halo(f) for f in unit.before] + [own] + [halo(f) for f in unit.after]
    first = sum(len(p) for p, _ in parts[: len(unit.before)])
    mine = slice(first, first + len(own[1]))
    cloud = DeviationCloud(np.concatenate([p for p, _ in parts]), np.concatenate([d for _, d in parts]))
    del parts, own
    local = local_deviations(cloud, b.lower_mm, b.upper_mm, b.smoothing_mm, unit.screen, mine)
    linked = linked_pieces(cloud, local, b.lower_mm, b.upper_mm, unit.link_mm)
    x = cloud.points_mm[linked.at] @ x_W[:3] + x_W[3]
    near = unit.link_mm * (1.0 + 1e-9) + 1e-6  # the rounding of x through F and back
    edge = (x <= lo + near) | (x >= hi - near)
    nearest = local.nearest_mm
    return TileAreas(unit.index, linked.pieces, cloud.points_mm[linked.at[edge]], linked.piece[edge],
                     np.bincount(np.searchsorted(SPACING_EDGES_MM, nearest), minlength=len(SPACING_EDGES_MM) + 1),
                     float(nearest.max()) if len(nearest) else 0.0)


def area_units(tiles: Sequence[TileDeviations], store: str | Path, T_F_W: np.ndarray, bounds: AreaBounds,
               link_mm: float) -> list[AreaTile]:
    """One :class:`AreaTile` a tile with points, its halo the tiles whose points' x comes within
    :data:`HALO_SMOOTHINGS` smoothing radii of its own; screened where all the tiles hold more than
    ``deviation_areas.THIN_ABOVE_POINTS`` points (as the untiled cloud would be)."""
    inspected = [t for t in tiles if t.count]
    screen = sum(t.count for t in inspected) > THIN_ABOVE_POINTS
    reach = HALO_SMOOTHINGS * bounds.smoothing_mm
    return [AreaTile(t.index, t.file, (t.x_min_mm, t.x_max_mm),
                     tuple(o.file for o in inspected[:k] if o.x_max_mm >= t.x_min_mm - reach),
                     tuple(o.file for o in inspected[k + 1:] if o.x_min_mm <= t.x_max_mm + reach),
                     str(store), np.asarray(T_F_W, float), bounds, link_mm, screen)
            for k, t in enumerate(inspected)]


def tile_areas(tiles: Sequence[TileDeviations], store: str | Path, T_F_W: np.ndarray, bounds: AreaBounds,
               backend: ComputeBackend) -> tuple[DeviationArea, ...]:
    """The deviation areas of all the tiles' points (F, mm) beyond ``bounds``, as ``find_deviation_areas`` finds
    them on the untiled cloud: :func:`find_tile_areas` of every tile on ``backend`` (:func:`area_units`), the pieces
    joined across the tiles here (:func:`joined_areas`). The points are linked within one smoothing radius first;
    where the spacing the tiles report may make the untiled link distance longer (three spacings), the units run
    again at a bound of it (their spacing's median to the 0.01 mm above)."""
    link = bounds.smoothing_mm
    while True:
        units = area_units(tiles, store, T_F_W, bounds, link)
        found = tuple(backend.map(find_tile_areas, units, [u.key() for u in units]))
        needed = link_distance(_spacing_bound(found), bounds.smoothing_mm)
        if needed <= link:
            return joined_areas(found, link, bounds.min_area_mm2)
        link = needed


def _spacing_bound(tiles: Sequence[TileAreas]) -> float:
    """A bound from above of the median of the tiles' nearest-neighbour distances (mm): the upper edge of the bin
    of :data:`SPACING_EDGES_MM` that holds the upper of its middle values."""
    counts = np.cumsum(sum(t.spacing_histogram for t in tiles))
    if not len(tiles) or counts[-1] == 0:
        return 0.0
    b = int(np.searchsorted(counts, counts[-1] // 2, side="right"))
    return float(SPACING_EDGES_MM[b]) if b < len(SPACING_EDGES_MM) else max(t.spacing_max_mm for t in tiles)


def joined_areas(tiles: Sequence[TileAreas], link_mm: float, min_area_mm2: float) -> tuple[DeviationArea, ...]:
    """The areas of the tiles' pieces joined where a linked point of one lies within ``link_mm`` of one of the same
    side in another tile (``deviation_areas.areas_of``: at least ``min_area_mm2``, largest |extreme| first)."""
    pieces = [p for t in tiles for p in t.pieces]
    if not pieces:
        return ()
    first = np.cumsum([0] + [len(t.pieces) for t in tiles])
    points = np.concatenate([t.edge_points_mm.reshape(-1, 3) for t in tiles])
    owner = np.concatenate([np.asarray(t.edge_pieces, np.int64) + first[k] for k, t in enumerate(tiles)])
    pairs = cKDTree(points).query_pairs(link_mm, output_type="ndarray") if len(points) else np.zeros((0, 2), int)
    upper = np.array([p.side == "upper" for p in pieces])
    a, b = owner[pairs[:, 0]], owner[pairs[:, 1]]
    same = upper[a] == upper[b]
    n, label = connected_components(coo_matrix((np.ones(int(same.sum())), (a[same], b[same])),
                                               shape=(len(pieces), len(pieces))), directed=False)
    whole: dict[int, AreaPiece] = {}
    for piece, c in zip(pieces, label.tolist(), strict=True):
        whole[c] = piece if c not in whole else whole[c].joined(piece)
    return areas_of(list(whole.values()), min_area_mm2)


#: the report sample's points an :class:`UncertaintyField` keeps (an even thinning beyond it): U is smooth over the
#: surface (its pose terms are evaluated at even centres, ``point_uncertainty.MAX_CENTRES``) and a worker holds
#: the field whole
FIELD_POINTS = 250_000


@dataclass(frozen=True)
class UncertaintyField:
    """The expanded uncertainty U (mm) of the report sample's points ``points_F_mm`` (F, mm): each point of the tiles
    takes its nearest one's (:meth:`at`). A thinning of the sample, so U's noise term is the sample's point's."""

    points_F_mm: np.ndarray
    expanded_mm: np.ndarray

    @classmethod
    def of(cls, points_F_mm: np.ndarray, expanded_mm: np.ndarray) -> UncertaintyField:
        """Every k-th of the sample's points and their U, at most :data:`FIELD_POINTS`."""
        step = max(1, -(-len(points_F_mm) // FIELD_POINTS))
        return cls(np.asarray(points_F_mm, float)[::step], np.asarray(expanded_mm, float)[::step])

    @functools.cached_property
    def _tree(self) -> cKDTree:
        return cKDTree(self.points_F_mm)

    def at(self, points_F_mm: np.ndarray) -> np.ndarray:
        """U of the field's nearest point to each of ``points_F_mm`` (F, mm)."""
        if len(points_F_mm) == 0:
            return np.empty(0)
        return self.expanded_mm[self._tree.query(points_F_mm, workers=-1)[1]]

    def write(self, store: str | Path) -> str:
        """Write the field into the scan store's tiles folder under the digest of its arrays; the file relative to
        ``store``."""
        h = hashlib.blake2b(digest_size=16)
        for a in (self.points_F_mm, self.expanded_mm):
            h.update(np.ascontiguousarray(a, np.float64).tobytes())
        file = f"{TILES_FOLDER}/uncertainty-{h.hexdigest()}.npz"
        write_durably(Path(store) / file, functools.partial(
            np.savez, points_F_mm=self.points_F_mm, expanded_mm=self.expanded_mm))
        return file


@functools.lru_cache(maxsize=1)
def _field(path: str) -> UncertaintyField:
    """The field in ``path``, read once a worker process (the units of a job share it)."""
    with np.load(path) as data:
        return UncertaintyField(data["points_F_mm"], data["expanded_mm"])


def write_cad(store: str | Path, surface: CadSurface) -> str:
    """The CAD mesh of ``surface`` (F, mm: vertices float64 and triangles as the job took them, before its
    ``reversed``) into the scan store's tiles folder under its digest, for the units to read to the bit; the file
    relative to ``store``."""
    vertices = np.asarray(surface.mesh.vertices, np.float64)
    triangles = np.asarray(surface.mesh.triangles, np.int64)
    h = hashlib.blake2b(digest_size=16)
    for a in (vertices, triangles):
        h.update(np.ascontiguousarray(a).tobytes())
    file = f"{TILES_FOLDER}/cad-{h.hexdigest()}.npz"
    write_durably(Path(store) / file, functools.partial(np.savez, vertices_mm=vertices, triangles=triangles))
    return file


@dataclass(frozen=True)
class WholeCloud:
    """What :meth:`TiledInspection.inspected` found of every point of the cloud: the report's deviation figures and
    the deviation areas beyond the bounds it was given (none where it was given none)."""

    figures: DeviationFigures
    areas: tuple[DeviationArea, ...]


@dataclass(frozen=True)
class TiledInspection:
    """A job's cloud merged by tiles (``tiles.TiledCloud``'s ``tiles`` in the scan store ``store``) as the inspection
    takes it beside the report's sample (module doc): :meth:`inspected` runs on ``backend``."""

    tiles: tuple[TileCloud, ...]
    store: str
    backend: ComputeBackend

    @property
    def count(self) -> int:
        """The cloud's points (voxels), those of the reference spheres included (``tiles.TiledCloud.count``)."""
        return sum(t.voxels for t in self.tiles)

    @contextlib.contextmanager
    def inspected(self, surface: CadSurface, T_F_W: np.ndarray, band_mm: tuple[float, float],
                  uncertainty: UncertaintyField | None, left_out: Sequence[tuple[np.ndarray, float]], ply: Path,
                  areas: AreaBounds | None = None) -> Iterator[InspectedTiles]:
        """Every tile placed in F by ``T_F_W`` (4x4, mm) and compared with ``surface`` (the CAD as the inspection
        oriented it: its ``reversed`` triangles) on the backend, each point with the U of ``uncertainty``'s nearest
        (None: no U), the points in the balls ``left_out`` ((centre W mm, radius mm): the reference spheres) left
        out: the deviation figures of the whole cloud in the band ``band_mm`` (lower, upper, mm), its deviation
        areas beyond ``areas`` (:func:`tile_areas`; None: none sought) and ``ply``, the deviation PLY, streamed. The
        units' files are kept while the block runs, for the points of small regions (:meth:`InspectedTiles.points_in`),
        and removed after. The heap this process freed since the report's sample was inspected (its temporaries,
        cloud.ply's blocks) is handed back first (``compute.trim_heap``), so that the tiles' stage and the PLY start
        from what is held."""
        trim_heap()
        lower, upper = band_mm
        cad = field = ""
        inspected: tuple[TileDeviations, ...] = ()
        try:
            cad = write_cad(self.store, surface)
            field = "" if uncertainty is None else uncertainty.write(self.store)
            sample = FromSample(field, tuple((*map(float, c), float(r)) for c, r in left_out))
            inspected = inspect_tiles(self.tiles, self.store, Path(self.store) / cad, T_F_W, lower, upper,
                                      self.backend, surface.reversed, sample)
            figures = deviation_figures(self.store, inspected, lower, upper)
            found = () if areas is None else tile_areas(inspected, self.store, T_F_W, areas, self.backend)
            write_deviation_ply(ply, self.store, inspected)
            yield InspectedTiles(WholeCloud(figures, found), tuple(t.file for t in inspected if t.count), self.store,
                                 self.backend)
        finally:
            for file in (cad, field, *(t.file for t in inspected)):
                if file:
                    (Path(self.store) / file).unlink(missing_ok=True)

    def placed_in(self, T_F_W: np.ndarray, regions: Sequence[Region]) -> np.ndarray:
        """The cloud's points (W, mm, in its order) that lie, placed in F by ``T_F_W`` (4x4, mm), in any of ``regions``
        (``region_points.gather_placed``: the datum patches' points, before the tiles are inspected)."""
        return gather_placed(self.tiles, self.store, T_F_W, regions, self.backend)


@dataclass(frozen=True)
class InspectedTiles:
    """A tiled cloud while its inspection's files are kept (:meth:`TiledInspection.inspected`): what it found of every
    point (``whole``) and its tiles' deviations ``files`` (in the cloud's order, relative to the scan store ``store``)
    that :meth:`points_in` reads on ``backend``."""

    whole: WholeCloud
    files: tuple[str, ...]
    store: str
    backend: ComputeBackend

    def points_in(self, regions: Sequence[Region]) -> tuple[RegionPoints, ...]:
        """Each region's points of the whole cloud (F, mm, in its order: ``region_points.gather``)."""
        return gather(self.files, self.store, regions, self.backend)
