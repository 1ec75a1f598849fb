"""A streaming world map: scans merged into a voxel grid with bounded memory.

Each occupied voxel (edge ``voxel_mm``) keeps the running sum of its points and normals and a count; the
map's cloud is the per-voxel mean. Memory grows with the measured surface area, not with the scan count.
Keys are the voxel indices packed in one int64 (21 bits per axis: +-1,048,575 voxels, over a kilometre at
1 mm), kept sorted so that merging a scan is a vectorised search-and-insert.
"""

from __future__ import annotations

import numpy as np
from tandemscan.pipeline import frames as F

_BITS = 21
_OFFSET = 1 << (_BITS - 1)


class VoxelMap:
    """Voxel-merged cloud in the world frame (mm)."""

    def __init__(self, voxel_mm: float = 1.0):
        if voxel_mm <= 0:
            raise ValueError("voxel_mm must be positive")
        self.voxel_mm = float(voxel_mm)
        self._keys = np.empty(0, np.int64)
        self._sums = np.empty((0, 6), np.float64)  # point sum xyz, normal sum xyz
        self._counts = np.empty(0, np.int64)

    def __len__(self) -> int:
        return len(self._keys)

    def _pack(self, points: np.ndarray) -> np.ndarray:
        idx = np.floor(points / self.voxel_mm).astype(np.int64) + _OFFSET
        if idx.min(initial=0) < 0 or idx.max(initial=0) >= (1 << _BITS):
            raise ValueError("points outside the map's extent (about +-1 km at 1 mm voxels)")
        return (idx[:, 0] << (2 * _BITS)) | (idx[:, 1] << _BITS) | idx[:, 2]

    def add(self, points_mm: np.ndarray, normals: np.ndarray | None = None) -> None:
        """Merge one scan (world frame, mm) into the map."""
        points_mm = np.asarray(points_mm, np.float64)
        if len(points_mm) == 0:
            return
        values = np.zeros((len(points_mm), 6))
        values[:, :3] = points_mm
        if normals is not None:
            values[:, 3:] = normals
        keys = self._pack(points_mm)
        order = np.argsort(keys, kind="stable")
        keys, values = keys[order], values[order]
        uniq, start = np.unique(keys, return_index=True)
        sums = np.add.reduceat(values, start, axis=0)
        counts = np.diff(np.r_[start, len(keys)])

        pos = np.searchsorted(self._keys, uniq)
        found = pos < len(self._keys)
        found[found] = self._keys[pos[found]] == uniq[found]
        np.add.at(self._sums, pos[found], sums[found])
        np.add.at(self._counts, pos[found], counts[found])
        new = ~found
        if new.any():
            self._keys = np.insert(self._keys, pos[new], uniq[new])
            self._sums = np.insert(self._sums, pos[new], sums[new], axis=0)
            self._counts = np.insert(self._counts, pos[new], counts[new])

    def add_scan(self, T_W_S: np.ndarray, points_S_mm: np.ndarray, normals_S: np.ndarray | None = None) -> None:
        """Eq. 1: merge a scan given in the scanner frame S, placed in the world by ``T_W_S`` (mm)."""
        normals = None if normals_S is None else F.rotate_vectors(T_W_S, normals_S)
        self.add(F.transform_points(T_W_S, points_S_mm), normals)

    def points(self) -> np.ndarray:
        """Mean point of every occupied voxel, (M, 3) mm."""
        return self._sums[:, :3] / self._counts[:, None]

    def normals(self) -> np.ndarray:
        """Mean unit normal of every occupied voxel (zero where no normals were given)."""
        n = self._sums[:, 3:]
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)

    def counts(self) -> np.ndarray:
        """Points merged into each voxel."""
        return self._counts.copy()

    @property
    def nbytes(self) -> int:
        """Memory held by the map (bytes)."""
        return self._keys.nbytes + self._sums.nbytes + self._counts.nbytes
