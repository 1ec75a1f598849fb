"""Thinning of clouds before registration (docs/registration.md, "Overlap"): a voxel grid and even spacing.

Points are (N, 3) arrays in any unit; a voxel edge is in the same unit (mm in the pipeline, radii of the
normalised cloud in ``deepmerge.register``).
"""

from __future__ import annotations

import numpy as np


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """Centroid of the points in each occupied voxel of edge ``voxel``."""
    keys = np.floor(points / voxel).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    out = np.zeros((len(counts), 3))
    np.add.at(out, inverse, points)
    return out / counts[:, None]


def thin_evenly(indices: np.ndarray, max_points: int) -> np.ndarray:
    """At most ``max_points`` of ``indices``, evenly spaced along them (scan order: evenly over the overlap)."""
    if len(indices) <= max_points:
        return indices
    return indices[np.linspace(0, len(indices) - 1, max_points).round().astype(int)]
