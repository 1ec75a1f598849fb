"""Surface normals of a point cloud by principal component analysis of the k nearest neighbours
(docs/registration.md, "Fine stage").

Points are an (N, 3) array in millimetres; a normal is the unit eigenvector of the smallest eigenvalue of the
covariance of the point's ``k`` nearest neighbours (the point itself included), as Open3D's
``estimate_normals`` with a KNN search computes it. The sign is not oriented: a point-to-plane residual
squared does not depend on it.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

#: points per block of the batched eigen-decomposition (bounds the (block, k, 3) neighbour array)
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
        X = X - X.mean(axis=1, keepdims=True)
        C = np.matmul(X.transpose(0, 2, 1), X) / k
        w, V = np.linalg.eigh(C)                   # ascending eigenvalues: column 0 is the normal
        n = V[:, :, 0]
        n[w[:, 2] <= 0.0] = (0.0, 0.0, 1.0)
        out[lo:lo + BLOCK_POINTS] = n
    return out
