"""A streaming world map: scans merged into a voxel grid with bounded memory.

Each occupied voxel (edge ``voxel_mm``) keeps the running sum of its points and normals and a count; the
map's cloud is the per-voxel mean. Memory grows with the measured surface area, not with the scan count.
Keys are the voxel indices packed in one int64 (21 bits per axis: +-1,048,575 voxels, over a kilometre at
1 mm). A scan is first reduced to its voxels by dense counting over its bounding box where that box holds
only a few voxels a point (no sort of its points), else by sorting its keys; its voxels wait in a batch that
is sorted and reduced alone when it holds as many voxels as the map (or the map is read), then added to the
map's sorted arrays in place and its new voxels inserted, so each voxel is moved O(log scans) times, not once per
scan.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from tandemscan.pipeline.registration.sampling import DENSE_BOX_PER_POINT, DENSE_BOX_VOXELS, occupied_voxels

_BITS = 21
_OFFSET = 1 << (_BITS - 1)
#: the batch of scans' voxels is merged into the map at this size at least (about 100 MB), times the map's
#: ``batch_share``
_MIN_BATCH_VOXELS = 2_000_000


def _x_key(x_index: int) -> int:
    """The least packed key of the voxels of x index ``x_index`` (x is the keys' top bits: they sort x first)."""
    return (int(x_index) + _OFFSET) << (2 * _BITS)


@dataclass(frozen=True, eq=False)
class ScanVoxels:
    """One scan's occupied voxels in W (``VoxelMap.scan_voxels``): packed keys, sorted; per voxel the sums of its
    points (mm) and normals, float64 (M, 6); its point counts (M,)."""

    keys: np.ndarray
    sums: np.ndarray
    counts: np.ndarray

    def __len__(self) -> int:
        return len(self.keys)

    def x_cut(self, x_edges: Sequence[int]) -> list[ScanVoxels]:
        """The voxels of x index in ``[x_edges[k], x_edges[k + 1])``, for each k (slices of these arrays: the keys
        are sorted x first)."""
        at = np.searchsorted(self.keys, [_x_key(x) for x in x_edges])
        return [ScanVoxels(self.keys[a:b], self.sums[a:b], self.counts[a:b]) for a, b in itertools.pairwise(at)]


class VoxelMap:
    """Voxel-merged cloud in the world frame (mm). ``x_voxels`` = ``(lo, hi)`` keeps only the voxels whose x index
    (``floor(x / voxel_mm)``, W) is in ``[lo, hi)``: one tile of the world (``tiles.merge_tile``). Each scan is
    voxelised whole and its voxels outside the tile dropped, so a voxel's sums are those the whole map has.

    ``batch_share`` (0 to 1]: the scans' voxels wait in the batch until it holds this share of the map's voxels (at
    least this share of ``_MIN_BATCH_VOXELS``), then merged into the map, so a merge holds the map twice and at most
    ``batch_share`` of its voxels and one scan's besides. 1 moves each voxel O(log scans) times (the fewest merges,
    where the map's time matters); less bounds its peak by the map's voxels alone, not by how the scans' repeated
    voxels fall into batches (a tile's unit, ``tiles.merge_tile``)."""

    def __init__(self, voxel_mm: float = 1.0, x_voxels: tuple[int, int] | None = None, batch_share: float = 1.0):
        if voxel_mm <= 0:
            raise ValueError("voxel_mm must be positive")
        if not 0.0 < batch_share <= 1.0:
            raise ValueError("batch_share must be in (0, 1]")
        self.voxel_mm = float(voxel_mm)
        self.batch_share = float(batch_share)
        self._x_window = None if x_voxels is None else (int(x_voxels[0]), int(x_voxels[1]))
        self._keys = np.empty(0, np.int64)
        self._sums = np.empty((0, 6), np.float64)  # point sum xyz, normal sum xyz
        self._counts = np.empty(0, np.int64)
        self._batch: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []   # scans' voxels not yet merged
        self._batch_voxels = 0

    def __len__(self) -> int:
        self._flush()
        return len(self._keys)

    def add(self, points_mm: np.ndarray, normals: np.ndarray | None = None) -> None:
        """Merge one scan (world frame, (N, 3) mm, unit normals (N, 3) or None) into the map."""
        points_mm = np.asarray(points_mm, np.float64)
        if len(points_mm) == 0:
            return
        normal_rows = None if normals is None else np.asarray(normals, np.float64).T.copy()
        self.add_voxels(ScanVoxels(*self._voxelise(points_mm.T.copy(), normal_rows)))

    def add_scan(self, T_W_S: np.ndarray, points_S_mm: np.ndarray, normals_S: np.ndarray | None = None) -> None:
        """Eq. 1: merge a scan given in the scanner frame S, placed in the world by ``T_W_S`` (mm)
        (:meth:`scan_voxels`)."""
        if len(points_S_mm) == 0:
            return
        self.add_voxels(self.scan_voxels(T_W_S, points_S_mm, normals_S))

    def scan_voxels(self, T_W_S: np.ndarray, points_S_mm: np.ndarray, normals_S: np.ndarray | None = None
                    ) -> ScanVoxels:
        """Eq. 1: the voxels (this map's edge, W) of a scan given in the scanner frame S, placed in the world by
        ``T_W_S`` (mm), without merging them: what :meth:`add_scan` merges (``tiles.place_scan`` cuts them by tile).

        Points and normals are rotated in float32 (as a raw scan stores them) relative to the scan's origin, so
        the rounding stays below 0.1 um within a metre of it; the voxel sums are kept in float64 and the
        translation added to them, not to every point."""
        if len(points_S_mm) == 0:
            return ScanVoxels(np.empty(0, np.int64), np.empty((0, 6)), np.empty(0, np.int64))
        T = np.asarray(T_W_S, np.float64)
        R = T[:3, :3].astype(np.float32)
        rows = R @ np.asarray(points_S_mm, np.float32).T                      # (3, N): x, y, z about the origin
        normal_rows = None if normals_S is None else R @ np.asarray(normals_S, np.float32).T
        return ScanVoxels(*self._voxelise(rows, normal_rows, T[:3, 3]))

    @classmethod
    def combined(cls, maps: Sequence[VoxelMap]) -> VoxelMap:
        """One map of every voxel of ``maps`` (one voxel edge), merged in a single sort-and-reduce; ``maps`` are
        left empty. Maps of a few tens of scans each, combined once, sort far fewer voxels than one map taking
        every scan, whose growing arrays each flush sorts again (a whole part's 369 scans, 8.2 M voxels: a median
        5.8 s on two threads in eight maps against 8.7 s in one; docs/end-of-job.md)."""
        if not maps:
            raise ValueError("no maps to combine")
        out = cls(maps[0].voxel_mm)
        for m in maps:
            if m.voxel_mm != out.voxel_mm:
                raise ValueError(f"maps of {m.voxel_mm} and {out.voxel_mm} mm voxels cannot be combined")
            m._flush()
            out._batch.append((m._keys, m._sums, m._counts))
            m._keys, m._sums, m._counts = np.empty(0, np.int64), np.empty((0, 6)), np.empty(0, np.int64)
        out._flush()
        return out

    def add_voxels(self, voxels: ScanVoxels) -> None:
        """Merge one scan's voxels (:meth:`scan_voxels`, this map's edge): those within the map's ``x_voxels``
        join the batch, merged once it holds ``batch_share`` of the map's. Voxels given scan by scan in one order
        make the same sums, bit for bit, however they were cut (``ScanVoxels.x_cut``), in maps of one
        ``batch_share``."""
        if self._x_window is not None:
            (voxels,) = voxels.x_cut(self._x_window)
        self._batch.append((voxels.keys, voxels.sums, voxels.counts))
        self._batch_voxels += len(voxels)
        if self._batch_voxels >= self.batch_share * max(len(self._keys), _MIN_BATCH_VOXELS):
            self._flush()

    def _flush(self) -> None:
        """Merge the batch into the sorted map: the batch's keys sorted alone (stable) and its sums reduced per key,
        then added where the map has the key already and the new keys inserted in order.

        The map is never sorted again nor copied beside a batch as large as it: a merge holds the map, the batch
        and, where it brings new voxels, the map's arrays once more (64 B a voxel) while they are inserted."""
        if not self._batch:
            return
        batch, self._batch, self._batch_voxels = self._batch, [], 0
        keys = np.concatenate([k for k, _, _ in batch])
        if not len(keys):  # scans with no voxel in the map's x window
            return
        order = np.argsort(keys, kind="stable")
        keys = keys[order]
        first = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
        keys = keys[first]
        counts = np.add.reduceat(np.concatenate([c for _, _, c in batch])[order], first)
        sums = np.concatenate([s for _, s, _ in batch])
        del batch  # the batch's sums: only their concatenation is left
        sums = np.add.reduceat(sums[order], first, axis=0)
        del order, first
        if not len(self._keys):
            self._keys, self._sums, self._counts = keys, sums, counts
            return
        at = np.searchsorted(self._keys, keys)
        known = at < len(self._keys)
        known[known] = self._keys[at[known]] == keys[known]
        self._sums[at[known]] += sums[known]
        self._counts[at[known]] += counts[known]
        new = ~known
        if new.any():
            at, keys, sums, counts = at[new], keys[new], sums[new], counts[new]
            self._keys = np.insert(self._keys, at, keys)
            self._counts = np.insert(self._counts, at, counts)
            self._sums = np.insert(self._sums, at, sums, axis=0)

    def _voxelise(self, rows: np.ndarray, normal_rows: np.ndarray | None, origin: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The scan's occupied voxels: sorted packed keys, per-voxel sums (point xyz, normal xyz), counts.

        The voxels are numbered densely within the scan's bounding box (x slowest, as in the packed key, so
        that the order carries over) and summed with ``bincount``; a box too large or too sparse for that (a
        coarse scan, a scan far from compact) falls back to sorting the keys."""
        origin = np.zeros(3) if origin is None else np.asarray(origin, np.float64)
        f = [r * rows.dtype.type(1.0 / self.voxel_mm) for r in rows]   # voxel coordinates about the origin
        for fk, o in zip(f, origin, strict=True):
            fk += fk.dtype.type(o / self.voxel_mm)
        lo = np.array([np.floor(fk.min()) for fk in f], np.int64)
        hi = np.array([np.floor(fk.max()) for fk in f], np.int64)
        if lo.min() + _OFFSET < 0 or hi.max() + _OFFSET >= (1 << _BITS):
            raise ValueError("points outside the map's extent (about +-1 km at 1 mm voxels)")
        shape = hi - lo + 1
        volume = int(np.prod(shape))
        kind = np.int32 if volume < (1 << 31) else np.int64
        idx = []                                              # voxel index within the box, >= 0: truncation floors
        for fk, low in zip(f, lo, strict=True):
            fk -= fk.dtype.type(low)
            idx.append(fk.astype(kind))
        if volume <= min(DENSE_BOX_VOXELS, DENSE_BOX_PER_POINT * len(idx[0])):  # sparser: sorting is faster
            local = idx[0] * kind(shape[1])
            local += idx[1]
            local *= kind(shape[2])
            local += idx[2]
            occupied, inverse, counts = occupied_voxels(local, volume)
            cells = [occupied // (shape[1] * shape[2]) + lo[0], (occupied // shape[2]) % shape[1] + lo[1],
                     occupied % shape[2] + lo[2]]
        else:
            keys, inverse, counts = np.unique(self._pack([i + low for i, low in zip(idx, lo, strict=True)]),
                                              return_inverse=True, return_counts=True)
            inverse, cells = inverse.ravel(), None
        sums = np.zeros((len(counts), 6))
        for k, column in enumerate(list(rows) + ([] if normal_rows is None else list(normal_rows))):
            sums[:, k] = np.bincount(inverse, weights=column, minlength=len(counts))
        sums[:, :3] += origin * counts[:, None]
        return (keys if cells is None else self._pack(cells)), sums, counts

    @staticmethod
    def _pack(idx: list[np.ndarray]) -> np.ndarray:
        """One int64 key per voxel from its x, y, z index arrays (see the module doc)."""
        return ((idx[0] + _OFFSET) << (2 * _BITS)) | ((idx[1] + _OFFSET) << _BITS) | (idx[2] + _OFFSET)

    def points(self) -> np.ndarray:
        """Mean point of every occupied voxel, (M, 3) mm."""
        self._flush()
        return self._sums[:, :3] / self._counts[:, None]

    def normals(self) -> np.ndarray:
        """Mean unit normal of every occupied voxel (zero where no normals were given)."""
        self._flush()
        n = self._sums[:, 3:]
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)

    def counts(self) -> np.ndarray:
        """Points merged into each voxel."""
        self._flush()
        return self._counts.copy()

    def frozen(self, dtype: type = np.float64) -> MapCloud:
        """The map's cloud once nothing more is merged into it: its mean points and unit normals (W, mm) computed
        once, as ``dtype`` (float32 halves them where only a score reads them). The map keeps its sums; the
        caller drops it to free them."""
        points, normals = self.points().astype(dtype, copy=False), self.normals().astype(dtype, copy=False)
        counts = self._counts.astype(np.int32)
        for a in (points, normals, counts):
            a.setflags(write=False)  # shared by every reader
        return MapCloud(self.voxel_mm, points, normals, counts)

    @property
    def nbytes(self) -> int:
        """Memory held by the map (bytes), its batch included."""
        self._flush()
        return self._keys.nbytes + self._sums.nbytes + self._counts.nbytes


@dataclass(frozen=True, eq=False)
class MapCloud:
    """A finished map's cloud (:meth:`VoxelMap.frozen`): one mean point and unit normal an occupied voxel of edge
    ``voxel_mm`` (W, mm; normals zero where none were merged). It reads as the map does (``points()``,
    ``normals()``, ``len``) and hands out the same arrays each time instead of computing them anew: the end of a
    job reads the cloud for ``cloud.ply``, the E57, the inspection and the score, a 20 M-voxel map's 480 MB each.
    48 bytes a voxel in float64, against the map's 64 and its sums' reductions."""

    voxel_mm: float
    points_mm: np.ndarray
    normals_unit: np.ndarray
    point_counts: np.ndarray | None = None  # points merged into each voxel (the noise of its mean)

    def __len__(self) -> int:
        return len(self.points_mm)

    def points(self) -> np.ndarray:
        """Mean point of every occupied voxel, (M, 3) mm (the stored array: read, not written)."""
        return self.points_mm

    def normals(self) -> np.ndarray:
        """Mean unit normal of every occupied voxel, (M, 3) (the stored array)."""
        return self.normals_unit

    def counts(self) -> np.ndarray | None:
        """Points merged into each voxel, (M,) (the stored array), None where not kept."""
        return self.point_counts
