"""Per-point structure fed to DeepMerge (docs/deepmerge.md): ``k x 7`` local and ``k x 14`` with the global part.

For a centre point ``p`` with k nearest neighbours ``q_1..q_k`` (the first is ``p`` itself):

- local structure, one row per neighbour: ``q_j - p`` (3), the neighbour's normal ``n_j`` (3), ``|q_j - p|`` (1);
- global structure, the same for every row: the decentralised point ``p - c`` (c: the cloud's centroid) (3),
  the decentralised farthest point of the cloud from ``p`` (3), their distance (1).

Normals come from the least-squares plane through each point's k neighbours (the plane minimising the sum of
squared orthogonal distances: its normal is the covariance eigenvector of the smallest eigenvalue) and are
flipped to a common reference direction, because a plane fit has no sign. Units are whatever the points use
(the network is fed normalised clouds, see ``register``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import ConvexHull, QhullError, cKDTree

LOCAL_DIM = 7
POINT_DIM = 14


class FeatureError(ValueError):
    """Bad input to the feature computation (shape, too few points, bad k)."""


def _check(points: ArrayLike, k: int) -> np.ndarray:
    P = np.asarray(points, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3:
        raise FeatureError(f"expected an (N, 3) array, got shape {P.shape}")
    if k < 3:
        raise FeatureError(f"k must be at least 3 for a plane fit, got {k}")
    if len(P) < k:
        raise FeatureError(f"need at least k={k} points, got {len(P)}")
    return P


def knn(points: np.ndarray, k: int, queries: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(distances, indices) of the k nearest neighbours of each query (default: every point, itself first)."""
    tree = cKDTree(points)
    d, i = tree.query(points if queries is None else queries, k=k)
    return np.asarray(d).reshape(-1, k), np.asarray(i).reshape(-1, k)


def reference_direction(points: ArrayLike) -> np.ndarray:
    """A deterministic unit direction to orient normals by: the cloud's axis of least spread.

    Its sign puts the largest-magnitude component positive, so two roughly aligned views of one surface get
    the same direction.
    """
    P = np.asarray(points, dtype=float)
    w, V = np.linalg.eigh(np.cov((P - P.mean(0)).T))
    d = V[:, 0]
    return d if d[np.argmax(np.abs(d))] >= 0 else -d


def plane_normals(points: ArrayLike, k: int, orient_to: ArrayLike | None = None) -> np.ndarray:
    """Unit normals (N, 3) of the least-squares plane through each point's k nearest neighbours.

    ``orient_to``: a direction; each normal is flipped to have a non-negative dot product with it
    (default :func:`reference_direction` of the cloud).
    """
    P = _check(points, k)
    _, idx = knn(P, k)
    Q = P[idx]                                          # (N, k, 3)
    Q = Q - Q.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", Q, Q) / k
    _, vecs = np.linalg.eigh(cov)                       # ascending eigenvalues
    normals = vecs[:, :, 0]
    ref = reference_direction(P) if orient_to is None else np.asarray(orient_to, dtype=float)
    normals[normals @ ref < 0] *= -1.0
    return normals


def local_structure(points: np.ndarray, normals: np.ndarray, centres: np.ndarray, k: int) -> np.ndarray:
    """``(M, k, 7)``: neighbour offsets, neighbour normals and distances for the points ``centres`` (indices)."""
    d, idx = knn(points, k, points[centres])
    offsets = points[idx] - points[centres][:, None, :]
    return np.concatenate([offsets, normals[idx], d[:, :, None]], axis=2)


def farthest_points(points: np.ndarray, centres: np.ndarray, chunk: int = 512) -> np.ndarray:
    """Index of the cloud point farthest from each centre (exact).

    The farthest point of a set always lies on its convex hull, so only hull vertices are searched; a flat
    or degenerate cloud (no 3D hull) falls back to every point. Chunked brute force over the candidates.
    """
    try:
        cand = ConvexHull(points).vertices
    except QhullError:
        cand = np.arange(len(points))
    Q = points[cand]
    sq = np.einsum("ij,ij->i", Q, Q)
    out = np.empty(len(centres), dtype=int)
    for s in range(0, len(centres), chunk):
        c = points[centres[s:s + chunk]]
        out[s:s + chunk] = cand[np.argmax(sq[None, :] - 2.0 * c @ Q.T, axis=1)]
    return out


def global_structure(points: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """``(M, 7)``: decentralised point, decentralised farthest point, their distance."""
    c = points.mean(axis=0)
    p = points[centres] - c
    f = points[farthest_points(points, centres)] - c
    return np.concatenate([p, f, np.linalg.norm(f - p, axis=1, keepdims=True)], axis=1)


def point_structure(
    points: ArrayLike,
    k: int,
    centres: ArrayLike | None = None,
    normals: ArrayLike | None = None,
    orient_to: ArrayLike | None = None,
) -> np.ndarray:
    """``(M, k, 14)`` float32 point structure of the ``centres`` (indices; default all points).

    Neighbourhoods and the global part use the whole cloud, so a subsample of centres keeps the local
    density of the full cloud. ``normals`` default to :func:`plane_normals` with ``orient_to``.
    """
    P = _check(points, k)
    C = np.arange(len(P)) if centres is None else np.asarray(centres, dtype=int)
    N = plane_normals(P, k, orient_to) if normals is None else np.asarray(normals, dtype=float)
    loc = local_structure(P, N, C, k)
    glo = global_structure(P, C)
    return np.concatenate([loc, np.repeat(glo[:, None, :], k, axis=1)], axis=2).astype(np.float32)
