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
    cells = np.floor(P / voxel).astype(np.int64)
    cells -= cells.min(axis=0)
    span = cells.max(axis=0) + 1                 # one int64 key per voxel, ordered as the (x, y, z) rows
    keys = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
    if np.all(keys[1:] > keys[:-1]):  # one point a voxel, in voxel order: its own thinning
        return P, np.ones(len(P))
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    sums = np.stack([np.bincount(inverse, weights=P[:, k], minlength=len(counts)) for k in range(3)], axis=1)
    return sums / counts[:, None], counts.astype(float)


def thin_evenly(indices: np.ndarray, max_points: int) -> np.ndarray:
    """At most ``max_points`` of ``indices``, evenly spaced along them (scan order: evenly over the overlap)."""
    if len(indices) <= max_points:
        return indices
    return indices[np.linspace(0, len(indices) - 1, max_points).round().astype(int)]
