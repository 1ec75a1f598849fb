"""The merge of a job's cloud by spatial tile (docs/compute.md, "Tiles"): memory bounded by the tile, not the part.

The world frame W is cut into slabs across its x axis, each a whole number of voxels of the merge (edge
``voxel_mm``): tile ``k`` holds the voxels whose x index ``floor(x / voxel_mm)`` is in ``[lo_k, hi_k)``. The scans
come by reference (:class:`TileScan`: the raw scan file in the scan store, its final pose ``T_W_S``, a bound of its
points' x in W, which sets the slabs' extent), never their points. The merge has two steps of units: a
:class:`PlaceScan` reads its scan once, voxelises it whole at its pose (``VoxelMap.scan_voxels``, as the untiled map
does) and writes its voxels of each slab they reach as a shard beside the scans (:class:`TileShard`); a
:class:`MergeTile` then merges its tile's shards, one at a time in the job's order of the scans, into a voxel map of
the tile's voxels (``VoxelMap(x_voxels=...)``), writes the tile's cloud (:func:`read_tile`) and removes the shards.
The scans are placed in waves along x and a tile is merged as soon as every scan that reaches it is placed
(:func:`place_waves`, :func:`merge_tiles`): the shards on disk at once are those about the front, not the part's.
Only a :class:`TileCloud` (the file, its voxel count) comes back. So each raw scan is read once, however many tiles
it reaches; a unit holds one scan, or one tile's voxels and one shard.

Equal to the untiled merge: a voxel lies in exactly one tile (the slabs are cut on voxel faces) and gets there the
same per-scan sums (each scan is voxelised whole, as the untiled map does, and only then cut), from every scan that
has a point in it; the shards of a tile come in the job's order, so the tile's sums are the ones a tile reading its
scans whole would make, bit for bit. The voxel keys sort x first, so the tiles' clouds one after the other are the
untiled cloud in its order; only the order in which a voxel's per-scan sums are added differs (the untiled merge
adds them by groups of scans): its mean is the same to the rounding of those sums, 1e-9 mm. The slabs span every
scan's bound of x, :func:`scan_x_extent` of its thinned copy widened by the margin (the thinning voxel's diagonal,
where a thinned centroid lies from the points of its voxel, and one merge voxel for the float32 rounding of the
placement).

A unit is idempotent (its files are named by the digest of everything they depend on; a tile written durably is
taken as it is where its unit runs again, its shards gone), so a unit lost with its worker is run again with the
same result.
"""

from __future__ import annotations

import bisect
import functools
import hashlib
import math
import shutil
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tandemscan.pipeline.compute import ComputeBackend
from tandemscan.pipeline.geometry.frames import transform_points
from tandemscan.pipeline.io import npz_blocks
from tandemscan.pipeline.io.durable import write_durably, write_replacing
from tandemscan.pipeline.io.export import PlyChunk, write_ply_streamed
from tandemscan.pipeline.io.npz_blocks import row_blocks
from tandemscan.pipeline.io.raw_scan import read_raw_scan
from tandemscan.pipeline.stitching.worldmap import ScanVoxels, VoxelMap

#: the tiles' clouds are written in this folder of the scan store
TILES_FOLDER = "tiles"
#: a tile's map merges its batch of scans' voxels at this share of its voxels (``VoxelMap(batch_share=...)``): a
#: unit's peak set by its tile's voxels, not by how its scans' repeated voxels fall into batches (at 1, the batch
#: up to the map's size: a worker's merge 0.77 / 0.89 GiB on the bands of docs/capacity.md, now 0.60 / 0.65)
TILE_BATCH_SHARE = 0.25


@dataclass(frozen=True)
class TileScan:
    """A scan by reference for the tile stages: its raw scan file (relative to the scan store), its final pose
    ``T_W_S`` (4x4, W, mm) and a bound of its points' x in W (mm, :func:`scan_x_extent`: every point within)."""

    file: str
    T_W_S: np.ndarray
    x_min_mm: float
    x_max_mm: float


def scan_x_extent(T_W_S: np.ndarray, thinned_S: np.ndarray, thin_voxel_mm: float, voxel_mm: float
                  ) -> tuple[float, float]:
    """A bound of the x (W, mm) of a scan's points from its copy thinned at ``thin_voxel_mm`` (S, mm;
    ``raw_scan.read_thinned_scan``) placed at ``T_W_S``: the copy's extent widened by the thinning voxel's
    diagonal (a point's distance to its voxel's centroid at most) and one merge voxel ``voxel_mm`` (the float32
    rounding of the merge's placement, and the floor to the voxel). (inf, -inf) for a scan without points."""
    return ScanReach.of(T_W_S, thinned_S).x_bound(T_W_S, thin_voxel_mm, voxel_mm)


@dataclass(frozen=True)
class ScanReach:
    """What bounds a scan's x in W at any pose, without its points: the x extent (W, mm) of its thinned copy at the
    pose ``T_W_S`` it was summarised at, and ``reach_mm``, the largest distance of the copy's points from the
    scanner's origin (S, mm). Made where the scan is read (``correction.summarise_scan``), so that the process that
    plans the tiles holds no scan's points."""

    T_W_S: np.ndarray
    x_min_mm: float
    x_max_mm: float
    reach_mm: float

    @classmethod
    def of(cls, T_W_S: np.ndarray, thinned_S: np.ndarray) -> ScanReach:
        """The reach of the thinned copy ``thinned_S`` (S, mm) at ``T_W_S``; x extent (inf, -inf) without points."""
        if len(thinned_S) == 0:
            return cls(np.asarray(T_W_S, float), math.inf, -math.inf, 0.0)
        x = transform_points(T_W_S, thinned_S)[:, 0]
        reach = float(np.sqrt(np.max(np.einsum("ij,ij->i", thinned_S, thinned_S, dtype=float))))
        return cls(np.asarray(T_W_S, float), float(x.min()), float(x.max()), reach)

    def x_bound(self, T_W_S: np.ndarray, thin_voxel_mm: float, voxel_mm: float) -> tuple[float, float]:
        """A bound of the x (W, mm) of the scan's points at the pose ``T_W_S``: the extent at :attr:`T_W_S` moved
        by the change of x's translation and widened by how far the change of the rotation's x row can move a
        point within :attr:`reach_mm` (Cauchy-Schwarz), then by the margin of :func:`scan_x_extent`. At the
        summarised pose itself, :func:`scan_x_extent` of the copy to the bit."""
        if self.x_min_mm > self.x_max_mm:
            return math.inf, -math.inf
        shift = float(T_W_S[0, 3] - self.T_W_S[0, 3])
        turn = float(np.linalg.norm(np.asarray(T_W_S[0, :3], float) - self.T_W_S[0, :3])) * self.reach_mm
        margin = math.sqrt(3.0) * thin_voxel_mm + voxel_mm
        return self.x_min_mm + shift - turn - margin, self.x_max_mm + shift + turn + margin


@dataclass(frozen=True)
class TileGrid:
    """Slabs of W across x, cut on the faces of voxels of edge ``voxel_mm``: tile ``k`` holds the voxels of x
    index in ``[x_edges[k], x_edges[k + 1])``."""

    voxel_mm: float
    x_edges: tuple[int, ...]

    @classmethod
    def over(cls, scans: Sequence[TileScan], voxel_mm: float, tile_mm: float) -> TileGrid:
        """Slabs about ``tile_mm`` wide (a whole number of voxels) over the x extent of ``scans`` (those with
        points)."""
        seen = [s for s in scans if s.x_min_mm <= s.x_max_mm]
        lo = min((s.x_min_mm for s in seen), default=0.0)
        hi = max((s.x_max_mm for s in seen), default=0.0)
        first, last = math.floor(lo / voxel_mm), math.floor(hi / voxel_mm) + 1
        width = max(1, round(tile_mm / voxel_mm))
        edges = list(range(first, last, width)) + [last]
        return cls(voxel_mm, tuple(edges) if last > first else (first, first + 1))

    def __len__(self) -> int:
        return len(self.x_edges) - 1

    def tile_of(self, x_mm: float) -> int:
        """The tile whose slab holds ``x_mm`` (W, mm; the first or last where it lies before or after them)."""
        return min(max(bisect.bisect_right(self.x_edges, math.floor(x_mm / self.voxel_mm)) - 1, 0), len(self) - 1)

    def bounds_mm(self, k: int) -> tuple[float, float]:
        """Tile ``k``'s slab ``[x0, x1)`` in W, mm."""
        return self.x_edges[k] * self.voxel_mm, self.x_edges[k + 1] * self.voxel_mm


@dataclass(frozen=True)
class PlaceScan:
    """One unit of the tiled merge's first step: scan ``order`` of the job, ``scan``, read once from the scan store
    ``store``, its voxels cut by the tiles of ``grid`` and each tile's written as a shard in the merge's folder
    ``folder`` (relative to ``store``)."""

    order: int
    scan: TileScan
    grid: TileGrid
    store: str
    folder: str

    def key(self) -> str:
        """The unit's name: the merge's folder (everything its shards depend on) and the scan's place in the job."""
        return f"place-scan-{self.order:05d}-{Path(self.folder).name}"


@dataclass(frozen=True)
class TileShard:
    """A scan's voxels within tile ``index`` (``worldmap.ScanVoxels``: keys, sums, counts), written by
    :func:`place_scan` to ``file`` (relative to the scan store)."""

    index: int
    file: str
    voxels: int


@dataclass(frozen=True)
class MergeTile:
    """One unit of the tiled merge's second step: tile ``index`` of ``grid`` and the shards of the scans that reach
    it (:class:`TileShard` files, in the job's order of the scans), in the scan store ``store`` (a folder every
    worker reaches)."""

    index: int
    grid: TileGrid
    shards: tuple[str, ...]
    store: str

    def key(self) -> str:
        """The unit's name: everything its cloud depends on (slab, voxel, its shards: named by the scans' files and
        poses)."""
        h = hashlib.blake2b(digest_size=16)
        h.update(np.array([self.grid.voxel_mm, *self.grid.bounds_mm(self.index)], np.float64).tobytes())
        for shard in self.shards:
            h.update(shard.encode())
        return f"merge-tile-{self.index:05d}-{h.hexdigest()}"


@dataclass(frozen=True)
class TileCloud:
    """A tile's merged cloud as the tiled merge wrote it: ``file`` (relative to the scan store: points and unit
    normals, W, mm, float64, and each voxel's point count, in voxel key order) and its ``voxels``."""

    index: int
    file: str
    voxels: int


def place_units(scans: Sequence[TileScan], grid: TileGrid, store: str) -> list[PlaceScan]:
    """One :class:`PlaceScan` a scan of ``scans`` (in the job's order), their shards in one folder of
    ``<store>/tiles`` named by the digest of the grid and every scan's file and pose."""
    h = hashlib.blake2b(digest_size=16)
    h.update(np.array([grid.voxel_mm, *grid.x_edges], np.float64).tobytes())
    for s in scans:
        h.update(s.file.encode())
        h.update(np.ascontiguousarray(s.T_W_S, np.float64).tobytes())
    folder = f"{TILES_FOLDER}/shards-{h.hexdigest()}"
    return [PlaceScan(k, s, grid, store, folder) for k, s in enumerate(scans)]


def place_scan(unit: PlaceScan) -> tuple[TileShard, ...]:
    """Read the unit's scan once (float32 as stored), place it at ``T_W_S`` (Eq. 1: voxelised whole, as the
    untiled map does, ``VoxelMap.scan_voxels``), cut its voxels by the grid's slabs and write each slab's that
    holds any to ``<folder>/<scan>-<tile>.npz``; their :class:`TileShard`, in tile order."""
    grid = unit.grid
    voxels = VoxelMap(grid.voxel_mm).scan_voxels(unit.scan.T_W_S,
                                                  *read_raw_scan(Path(unit.store) / unit.scan.file, np.float32))
    shards = []
    for k, cut in enumerate(voxels.x_cut(grid.x_edges)):
        if len(cut):
            file = f"{unit.folder}/{unit.order:05d}-{k:05d}.npz"
            write_replacing(Path(unit.store) / file, functools.partial(  # the job's end places its scans again
                np.savez, keys=cut.keys, sums=cut.sums, counts=cut.counts))
            shards.append(TileShard(k, file, len(cut)))
    return tuple(shards)


def tile_units(placed: Sequence[Sequence[TileShard]], grid: TileGrid, store: str) -> list[MergeTile]:
    """One :class:`MergeTile` a tile of ``grid``: the shards of it among ``placed`` (each scan's, :func:`place_scan`,
    in the job's order)."""
    shards: list[list[str]] = [[] for _ in range(len(grid))]
    for scan in placed:
        for shard in scan:
            shards[shard.index].append(shard.file)
    return [MergeTile(k, grid, tuple(files), store) for k, files in enumerate(shards)]


def merge_tile(unit: MergeTile) -> TileCloud:
    """Merge the unit's shards (read one at a time, in the job's order of their scans) into its tile's voxels (a
    map of :data:`TILE_BATCH_SHARE`), write them to ``<store>/tiles/<unit key>.npz`` and remove the shards. Where
    that file is there already (written durably: whole) the unit ran before and removed its shards: it is taken as
    it is."""
    store = Path(unit.store)
    file = f"{TILES_FOLDER}/{unit.key()}.npz"
    if (store / file).is_file():
        with np.load(store / file) as data:
            voxels = len(data["counts"])
    else:
        worldmap = VoxelMap(unit.grid.voxel_mm, (unit.grid.x_edges[unit.index], unit.grid.x_edges[unit.index + 1]),
                            TILE_BATCH_SHARE)
        for shard in unit.shards:
            with np.load(store / shard) as data:
                worldmap.add_voxels(ScanVoxels(data["keys"], data["sums"], data["counts"]))
        cloud = worldmap.frozen()
        del worldmap
        write_durably(store / file, functools.partial(
            np.savez, points=cloud.points(), normals=cloud.normals(), counts=np.asarray(cloud.counts(), np.int64)))
        voxels = len(cloud)
    for shard in unit.shards:
        (store / shard).unlink(missing_ok=True)
    return TileCloud(unit.index, file, voxels)



def place_waves(placing: Sequence[PlaceScan], grid: TileGrid) -> list[tuple[int, tuple[PlaceScan, ...]]]:
    """The placing of the scans in waves along x: each wave the units of the scans whose bound of x starts in tile
    ``first`` of ``grid`` (those without points in tile 0's), as ``(first, units)`` in x order. Every tile before
    ``first`` is complete once the waves before it are placed: the scans that reach it are theirs."""
    by_tile: dict[int, list[PlaceScan]] = {}
    for u in placing:
        first = grid.tile_of(u.scan.x_min_mm) if u.scan.x_min_mm <= u.scan.x_max_mm else 0
        by_tile.setdefault(first, []).append(u)
    return [(first, tuple(by_tile[first])) for first in sorted(by_tile)]


def run_merge_unit(unit: PlaceScan | MergeTile) -> tuple[TileShard, ...] | TileCloud:
    """A unit of either step of the tiled merge (one map of :func:`merge_tiles` runs both): :func:`place_scan` or
    :func:`merge_tile`."""
    return place_scan(unit) if isinstance(unit, PlaceScan) else merge_tile(unit)


def _not_in_merged(unit: PlaceScan, shards: tuple[TileShard, ...], merged: int) -> tuple[TileShard, ...]:
    """The shards of a placed scan, checked against the waves' invariant: none in the first ``merged`` tiles, whose
    merges were handed out with or before its wave. A shard there would be left out of its tile: the scan's bound of
    x (``TileScan.x_min_mm``) did not bound its points, and the merge stops (ValueError) rather than drop them."""
    late = sorted({s.index for s in shards if s.index < merged})
    if late:
        raise ValueError(f"scan {unit.order} ({unit.scan.file}) has voxels in tiles {late}, merged before its wave: "
                         f"its bound of x from {unit.scan.x_min_mm:.3f} mm does not bound its points")
    return shards


def merge_tiles(scans: Sequence[TileScan], voxel_mm: float, tile_mm: float, store: str | Path,
                backend: ComputeBackend) -> tuple[TileCloud, ...]:
    """The job's cloud merged tile by tile on ``backend`` (W, mm), in x order: the tiles' clouds one after the other
    are the untiled cloud (module doc). Two steps of units: each scan read once, placed and cut into shards by the
    slabs about ``tile_mm`` wide (:func:`place_scan`), then each tile merged from its shards (:func:`merge_tile`).
    The scans are placed in waves along x (:func:`place_waves`), one map each, which also merges the tiles the waves
    before it completed: so the shards on disk at once are those of the tiles about the front (of the scans of two
    waves), not the part's (docs/compute.md, "Tiles"). Where a unit fails (or is cancelled), the
    shards and the tiles written so far are removed. The heap the tiles' voxels took is handed back once they are
    written (``ComputeBackend.trim``), so that the next stage starts from what the workers hold, not from the
    largest tile's peak."""
    grid = TileGrid.over(scans, voxel_mm, tile_mm)
    placing = place_units(scans, grid, str(store))
    placed: list[tuple[TileShard, ...]] = [()] * len(placing)
    merging: list[MergeTile] = []  # every tile's unit handed to a map so far, in tile order
    merged: list[TileCloud] = []
    try:
        for first, wave in [*place_waves(placing, grid), (len(grid), ())]:  # then the tiles after the last wave
            ready = tile_units(placed, grid, str(store))[len(merging):first]  # their scans all placed
            merging += ready
            units = [*ready, *wave]  # the merges first: their shards leave the disk before the wave's come
            for u, out in zip(units, backend.map(run_merge_unit, units, [u.key() for u in units]), strict=True):
                if isinstance(u, PlaceScan):
                    placed[u.order] = _not_in_merged(u, out, len(merging))
                else:
                    merged.append(out)
    except BaseException:
        for u in merging:
            (Path(store) / TILES_FOLDER / f"{u.key()}.npz").unlink(missing_ok=True)
        raise
    finally:
        if placing:
            shutil.rmtree(Path(store) / placing[0].folder, ignore_errors=True)
    backend.trim()
    return tuple(merged)


@dataclass(frozen=True)
class TilePoints:
    """A tile's cloud read back: mean points and unit normals (W, mm, float64), each voxel's point count (None: a
    cloud that kept none)."""

    points_mm: np.ndarray
    normals: np.ndarray
    counts: np.ndarray | None


def read_tile(store: str | Path, tile: TileCloud) -> TilePoints:
    """Tile ``tile``'s cloud from the scan store ``store``."""
    with np.load(Path(store) / tile.file) as data:
        return TilePoints(data["points"], data["normals"], data["counts"])


def _ply_chunks(store: str | Path, tiles: Sequence[TileCloud]) -> Iterator[PlyChunk]:
    """The tiles' points and normals in turn, ``npz_blocks.BLOCK_ROWS`` rows at a time read from their files when
    the writer asks for them (``npz_blocks.row_blocks``): one block in memory at a time, never a whole tile."""
    for tile in tiles:
        for block in row_blocks(Path(store) / tile.file, ("points", "normals"), npz_blocks.BLOCK_ROWS):
            yield PlyChunk(block["points"], block["normals"])


def write_cloud_ply(path: Path, store: str | Path, tiles: Sequence[TileCloud]) -> Path:
    """``cloud.ply`` (W, mm: points and unit normals) streamed from the tiles' clouds, the vertex count known from
    their voxel counts: the bytes ``export.write_ply`` writes of the untiled cloud, to the rounding of the merge."""
    return write_ply_streamed(path, sum(t.voxels for t in tiles), _ply_chunks(store, tiles))


def every_kth(store: str | Path, tiles: Sequence[TileCloud], step: int) -> TilePoints:
    """The cloud's every ``step``-th voxel, counted over the tiles one after the other (the untiled cloud's
    ``[::step]``: what the alignment to the CAD and the report's figures take, ``[inspection] max_points``), read
    a block of rows of a tile at a time (``npz_blocks.row_blocks``) into arrays of the sample's size: the sample and
    one block held, never a tile or the cloud."""
    total = sum(t.voxels for t in tiles)
    out: TilePoints | None = None
    offset = 0  # voxels before the block
    for tile in tiles:
        if (-offset) % step >= tile.voxels:  # no sampled voxel in this tile
            offset += tile.voxels
            continue
        for block in row_blocks(Path(store) / tile.file, ("points", "normals", "counts"), npz_blocks.BLOCK_ROWS):
            if out is None:
                out = TilePoints(*(np.empty((len(range(0, total, step)), *block[name].shape[1:]), block[name].dtype)
                                   for name in ("points", "normals", "counts")))
            first, rows = (-offset) % step, len(block["points"])
            at = slice(-(-offset // step), -(-(offset + rows) // step))  # the sample's rows of this block
            out.points_mm[at], out.normals[at], out.counts[at] = (
                block[name][first::step] for name in ("points", "normals", "counts"))
            offset += rows
    return out or TilePoints(np.empty((0, 3)), np.empty((0, 3)), np.empty(0, np.int64))


@dataclass(frozen=True)
class TiledCloud:
    """A job's cloud merged by tiles (:func:`merge_tiles`), left in its tiles' files in the scan store ``store``:
    voxels of edge ``voxel_mm``, W, mm, the tiles one after the other in the untiled cloud's order. The end of a job
    takes it where it would take the whole cloud and reads it a tile at a time: ``cloud.ply`` (:meth:`write_ply`),
    the E57's merged scan (:meth:`bounds_mm`, :meth:`blocks`: ``export.PointBlocks``), the inspected subsample
    (:meth:`every_kth`); :meth:`points` reads it whole, for the simulator's observer alone."""

    voxel_mm: float
    store: str
    tiles: tuple[TileCloud, ...]

    def __len__(self) -> int:
        return sum(t.voxels for t in self.tiles)

    @property
    def count(self) -> int:
        """The cloud's points (voxels)."""
        return len(self)

    def bounds_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """Per axis the smallest and largest point coordinate (mm), a tile read at a time."""
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for block in self.blocks():
            if len(block):
                lo, hi = np.minimum(lo, block.min(axis=0)), np.maximum(hi, block.max(axis=0))
        return lo, hi

    def blocks(self) -> Iterator[np.ndarray]:
        """Each tile's points (mm) in turn, read when asked for."""
        for tile in self.tiles:
            with np.load(Path(self.store) / tile.file) as data:
                points = data["points"]
            yield points

    def write_ply(self, path: Path) -> Path:
        """``cloud.ply`` streamed from the tiles (:func:`write_cloud_ply`)."""
        return write_cloud_ply(path, self.store, self.tiles)

    def every_kth(self, step: int) -> TilePoints:
        """The cloud's every ``step``-th voxel (:func:`every_kth`), a block of a tile read at a time."""
        return every_kth(self.store, self.tiles, step)

    def points(self) -> np.ndarray:
        """Every point (mm), read whole: the simulator's observer's score of the cloud, never the product's."""
        return np.concatenate(list(self.blocks())) if self.tiles else np.empty((0, 3))

    def remove(self) -> None:
        """Delete the tiles' files (once the cloud's exports are written)."""
        for t in self.tiles:
            (Path(self.store) / t.file).unlink(missing_ok=True)
