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
1e-9 mm (``tests/pipeline/stitching/test_tiles.py``).
"""

from __future__ import annotations

import functools
import hashlib
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tandemscan.pipeline.compute import ComputeBackend
from tandemscan.pipeline.geometry.frames import rotate_vectors, transform_points
from tandemscan.pipeline.geometry.part import read_cad_mesh
from tandemscan.pipeline.inspection.inspect import CadSurface, DeviationStats, ToleranceResult, in_chunks
from tandemscan.pipeline.io.durable import write_durably
from tandemscan.pipeline.io.export import PlyChunk, write_ply_streamed
from tandemscan.pipeline.stitching.tiles import TileCloud, read_tile

#: the edges (mm) of the deviation histogram each tile returns (0.01 mm bins over +-20 mm, and one bin beyond each
#: end): only a bin's count travels, the percentiles are found exactly from its values (:func:`deviation_figures`)
HISTOGRAM_EDGES_MM = np.linspace(-20.0, 20.0, 4001)


@dataclass(frozen=True)
class InspectTile:
    """One unit of the tiled inspection: the tile ``tile`` of the merged cloud in the scan store ``store``, placed
    in the CAD frame F by ``T_F_W`` (4x4, mm) and compared with the CAD mesh file ``mesh_file`` (F; its coordinates
    in ``mesh_units``, read as the job reads its CAD, ``part.read_cad_mesh``: in mm, wound outward; its triangles
    ``reversed`` wound the other way: ``CadSurface``), the tolerance band ``[lower_mm, upper_mm]``."""

    tile: TileCloud
    store: str
    mesh_file: str
    T_F_W: np.ndarray
    lower_mm: float
    upper_mm: float
    reversed: np.ndarray | None = None
    mesh_units: str = "mm"

    def key(self) -> str:
        """The unit's name: everything its deviations depend on."""
        h = hashlib.blake2b(digest_size=16)
        for text in (self.tile.file, self.mesh_file, self.mesh_units):
            h.update(text.encode())
        h.update(np.ascontiguousarray(self.T_F_W, np.float64).tobytes())
        h.update(np.array([self.lower_mm, self.upper_mm], np.float64).tobytes())
        if self.reversed is not None:
            h.update(np.packbits(np.asarray(self.reversed, bool)).tobytes())
        return f"inspect-tile-{self.tile.index:05d}-{h.hexdigest()}"


@dataclass(frozen=True)
class TileDeviations:
    """A tile's inspection: its deviations' file (relative to the scan store: points and unit normals in F, mm,
    float64, signed deviations ``deviation_mm``, + along the CAD's outward normal) and their summary (mm, mm^2)."""

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


@functools.lru_cache(maxsize=2)
def _surface(mesh_file: str, units: str, reversed_bits: bytes | None, triangles: int) -> CadSurface:
    """The CAD surface of ``mesh_file`` (coordinates in ``units``) as the job takes it (``part.read_cad_mesh``: mm,
    wound outward), built once a worker process (the units of a job share it)."""
    reversed = None if reversed_bits is None else np.unpackbits(
        np.frombuffer(reversed_bits, np.uint8), count=triangles).astype(bool)
    return CadSurface(read_cad_mesh(mesh_file, units, "CAD mesh"), reversed)


def _bins(deviations_mm: np.ndarray) -> np.ndarray:
    """The histogram bin of each deviation (0: below the first edge, len(edges): from the last one on)."""
    return np.searchsorted(HISTOGRAM_EDGES_MM, deviations_mm, side="right")


def inspect_tile(unit: InspectTile) -> TileDeviations:
    """The deviations of the unit's tile from the CAD, written to ``<store>/tiles/<unit key>.npz``, and their
    summary."""
    cloud = read_tile(unit.store, unit.tile)
    reversed = unit.reversed
    surface = _surface(unit.mesh_file, unit.mesh_units, None if reversed is None else np.packbits(reversed).tobytes(),
                       0 if reversed is None else len(reversed))
    T = np.asarray(unit.T_F_W, float)
    points_F = in_chunks(transform_points, T, cloud.points_mm)
    normals_F = in_chunks(rotate_vectors, T, cloud.normals)
    d = surface.closest(points_F).signed_mm if len(points_F) else np.empty(0)
    file = f"{Path(unit.tile.file).parent.as_posix()}/{unit.key()}.npz"
    write_durably(Path(unit.store) / file, functools.partial(
        _save, points_F=points_F, normals_F=normals_F, deviation_mm=d))
    n = len(d)
    mean = float(d.mean()) if n else 0.0
    return TileDeviations(
        unit.tile.index, file, n, mean, float(((d - mean) ** 2).sum()), float((d * d).sum()),
        float(d.min()) if n else math.inf, float(d.max()) if n else -math.inf,
        int(np.count_nonzero(d < unit.lower_mm)), int(np.count_nonzero(d > unit.upper_mm)),
        np.bincount(_bins(d), minlength=len(HISTOGRAM_EDGES_MM) + 1))


def _save(f, **arrays: np.ndarray) -> None:
    np.savez(f, **arrays)


def inspect_tiles(tiles: Sequence[TileCloud], store: str | Path, mesh_file: str | Path, T_F_W: np.ndarray,
                  lower_mm: float, upper_mm: float, backend: ComputeBackend,
                  reversed: np.ndarray | None = None, mesh_units: str = "mm") -> tuple[TileDeviations, ...]:
    """:func:`inspect_tile` of every tile on ``backend``, in the tiles' order (:class:`InspectTile` for the
    arguments).

    Nine parameters: the tiles, where they and the mesh lie, the placement in F, the band, the CAD's orientation
    and units (the fields of an :class:`InspectTile` unit) and the backend."""
    units = [InspectTile(t, str(store), str(mesh_file), np.asarray(T_F_W, float), lower_mm, upper_mm, reversed,
                         mesh_units) for t in tiles]
    return tuple(backend.map(inspect_tile, units, [u.key() for u in units]))


def _read_deviations(store: str | Path, tile: TileDeviations, *names: str) -> list[np.ndarray]:
    with np.load(Path(store) / tile.file) as data:
        return [data[name] for name in names]


def _deviation_chunks(store: str | Path, tiles: Sequence[TileDeviations]) -> Iterator[PlyChunk]:
    """The deviation PLY's vertices a tile at a time (F, mm: points, unit normals, ``deviation_mm``)."""
    for tile in tiles:
        points, normals, d = _read_deviations(store, tile, "points_F", "normals_F", "deviation_mm")
        yield PlyChunk(points, normals, {"deviation_mm": d})


def write_deviation_ply(path: Path, store: str | Path, tiles: Sequence[TileDeviations]) -> Path:
    """The deviation PLY (F, mm: points, unit normals, ``deviation_mm``) streamed a tile at a time, the vertex
    count known from the tiles' summaries."""
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
        (d,) = _read_deviations(store, t, "deviation_mm")
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
