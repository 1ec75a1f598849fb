"""Point-to-plane ICP, its scoring and the information of a fit (docs/registration.md, "Fine stage").

All clouds are (N, 3) arrays in millimetres; a result's ``transformation`` is ``T_target_source`` (4x4 mm,
maps source coordinates into the target's frame). The target carries normals (estimated once per pair by
:func:`target_with_normals`); residuals are distances along the target normal (mm).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree


class RefineError(ValueError):
    """Bad input to ICP or the pose graph (shapes, indices, covariances that are not positive definite)."""


@dataclass(frozen=True)
class IcpResult:
    """``T_target_source`` (4x4 mm); inlier fraction of the source; point-to-plane RMS of the inliers (mm);
    the inlier source points moved by the result and their target normals (for the edge information)."""

    transformation: np.ndarray
    fitness: float
    rmse_mm: float
    points_mm: np.ndarray
    normals: np.ndarray

    @property
    def inliers(self) -> int:
        return len(self.points_mm)


def _pcd(points: np.ndarray) -> o3d.geometry.PointCloud:
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=float)))


def target_with_normals(target_mm: ArrayLike | o3d.geometry.PointCloud, normal_neighbours: int = 20
                        ) -> o3d.geometry.PointCloud:
    """The target of a point-to-plane fit, with normals (k nearest neighbours); prepare it once per pair."""
    if isinstance(target_mm, o3d.geometry.PointCloud):
        return target_mm
    T = np.asarray(target_mm, float)
    if T.ndim != 2 or T.shape[1] != 3 or len(T) < normal_neighbours:
        raise RefineError(f"a point-to-plane target needs an (N, 3) cloud with N >= {normal_neighbours}; got {T.shape}")
    tgt = _pcd(T)
    tgt.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(normal_neighbours))
    return tgt


def icp_point_to_plane(
    source_mm: ArrayLike,
    target_mm: ArrayLike | o3d.geometry.PointCloud,
    init: ArrayLike | None = None,
    max_distance_mm: float = 2.0,
    iterations: int = 50,
    normal_neighbours: int = 20,
) -> IcpResult:
    """Point-to-plane ICP (Open3D) of ``source`` onto ``target`` from ``init`` (default identity)."""
    S = np.asarray(source_mm, float)
    if S.ndim != 2 or S.shape[1] != 3:
        raise RefineError(f"ICP needs an (N, 3) source cloud; got {S.shape}")
    tgt = target_with_normals(target_mm, normal_neighbours)
    reg = o3d.pipelines.registration
    res = reg.registration_icp(
        _pcd(S), tgt, max_distance_mm, np.eye(4) if init is None else np.asarray(init, float),
        reg.TransformationEstimationPointToPlane(),
        reg.ICPConvergenceCriteria(relative_fitness=1e-9, relative_rmse=1e-9, max_iteration=iterations),
    )
    return evaluate_point_to_plane(S, tgt, np.asarray(res.transformation), max_distance_mm)


def evaluate_point_to_plane(
    source_mm: ArrayLike, target: ArrayLike | o3d.geometry.PointCloud, T: ArrayLike, max_distance_mm: float,
    normal_neighbours: int = 20,
) -> IcpResult:
    """Score ``T_target_source`` without moving it: nearest-neighbour inliers within ``max_distance_mm``."""
    S = np.asarray(source_mm, float)
    tgt = target_with_normals(target, normal_neighbours)
    M = np.asarray(T, float).copy()
    Tp = np.asarray(tgt.points)
    moved = S @ M[:3, :3].T + M[:3, 3]
    d, idx = cKDTree(Tp).query(moved, k=1, distance_upper_bound=max_distance_mm)
    ok = np.isfinite(d)
    normals = np.asarray(tgt.normals)[idx[ok]]
    r = np.einsum("ij,ij->i", moved[ok] - Tp[idx[ok]], normals)
    rmse = float(np.sqrt(np.mean(r**2))) if ok.any() else float("inf")
    return IcpResult(M, float(ok.mean()) if len(S) else 0.0, rmse, moved[ok], normals)


def point_to_plane_information(
    points_mm: ArrayLike, normals: ArrayLike, centre_mm: ArrayLike, sigma_mm: float, effective_points: float
) -> np.ndarray:
    """6x6 information (t, r order, about ``centre_mm``) of a rigid fit to points on planes with normals.

    Each point constrains ``n . (dt + dr x (p - c))``; the sum of ``J^T J`` is scaled to ``effective_points``
    independent points of 1-sigma ``sigma_mm`` (neighbouring scan points are far from independent).
    """
    P = np.asarray(points_mm, float) - np.asarray(centre_mm, float)
    N = np.asarray(normals, float)
    J = np.c_[N, np.cross(P, N)]
    return (J.T @ J) / len(P) * effective_points / sigma_mm**2

