"""Thinning of clouds before registration (docs/registration.md): a voxel grid and even spacing.

Points are (N, 3) arrays in any unit; a voxel edge is in the same unit (mm in the pipeline, radii of the
normalised cloud in ``deepmerge.register``).
"""

from __future__ import annotations

import numpy as np


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """Centroid of the points in each occupied voxel of edge ``voxel``, in lexicographic (x, y, z) order of
    the voxel indices. A cloud that is its own thinning (one point a voxel, already in that order: a copy
    thinned before, as the end of a job keeps them) is returned as it is (float64), not copied."""
    return voxel_centroids(points, voxel)[0]


def voxel_centroids(points: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`voxel_downsample` and how many of ``points`` each centroid averages (float64, at least 1): a
    centroid of ``n`` points with independent noise errs by ``1 / sqrt(n)`` of one point's."""
    P = np.asarray(points, float)
    if len(P) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    cells = [np.floor(P[:, k] / voxel).astype(np.int64) for k in range(3)]  # by axis: contiguous reductions
    for c in cells:
        c -= c.min()
    span = [int(c.max()) + 1 for c in cells]     # one int64 key per voxel, ordered as the (x, y, z) rows
    keys = cells[0] * span[1]
    keys += cells[1]
    keys *= span[2]
    keys += cells[2]
    del cells
    if np.all(keys[1:] > keys[:-1]):  # one point a voxel, in voxel order: its own thinning
        return P, np.ones(len(P))
    volume = span[0] * span[1] * span[2]
    if volume <= min(DENSE_BOX_VOXELS, DENSE_BOX_PER_POINT * len(P)):  # a scan's box: counted, not sorted
        _, inverse, counts = occupied_voxels(keys, volume)
    else:
        _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    sums = np.stack([np.bincount(inverse, weights=P[:, k], minlength=len(counts)) for k in range(3)], axis=1)
    return sums / counts[:, None], counts.astype(float)


#: a cloud whose bounding box holds at most this many voxels (int64 counts: 128 MB) and at most
#: ``DENSE_BOX_PER_POINT`` voxels a point has its voxels counted densely over the box (:func:`occupied_voxels`), not
#: sorted: a full-resolution scan (3.2 M points, a box of 0.1 to 3 voxels a point at 1 mm) in a fraction of the time;
#: sorting is faster from about seven voxels a point on (a coarse scan of 40 k points in a 14 M voxel box: 4 against
#: 40 ms; ``stitching.worldmap`` counts a scan's voxels in W by the same rule)
DENSE_BOX_VOXELS = 16_000_000
DENSE_BOX_PER_POINT = 6


def occupied_voxels(index: np.ndarray, volume: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``np.unique(index, return_inverse=True, return_counts=True)`` of voxel numbers ``index`` in
    ``[0, volume)`` (a box's voxels numbered densely), by counting over the box instead of sorting: the occupied
    numbers in order, each entry's rank among them (``index``'s integer type) and each one's count."""
    counts = np.bincount(index, minlength=volume)
    occupied = np.flatnonzero(counts)
    rank = np.empty(volume, index.dtype)
    rank[occupied] = np.arange(len(occupied), dtype=index.dtype)
    return occupied, rank[index], counts[occupied]


def thin_evenly(indices: np.ndarray, max_points: int) -> np.ndarray:
    """At most ``max_points`` of ``indices``, evenly spaced along them (scan order: evenly over the overlap)."""
    if len(indices) <= max_points:
        return indices
    return indices[np.linspace(0, len(indices) - 1, max_points).round().astype(int)]
