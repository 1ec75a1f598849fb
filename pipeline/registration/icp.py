"""Point-to-plane ICP, its coarse-to-fine schedule, its scoring and the information of a fit
(docs/registration.md, "Fine stage").

All clouds are (N, 3) arrays in millimetres; a result's ``transformation`` is ``T_target_source`` (4x4 mm,
maps source coordinates into the target's frame). The target carries normals (estimated once per cloud by
:func:`target_with_normals`); residuals are distances along the target normal (mm).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree
from tandemscan.pipeline.registration.overlap import extract_overlap
from tandemscan.pipeline.registration.sampling import thin_evenly


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


@dataclass(frozen=True)
class FineSchedule:
    """The coarse-to-fine schedule of :func:`icp_coarse_to_fine`: the correspondence distance starts at
    ``start_mm`` and ends at ``final_mm``; after each level the next is ``shrink`` times the last, or
    ``rms_multiple`` times the level's point-to-plane RMS if that is smaller (a converged fit jumps to the
    end), never below ``final_mm``. ``iterations`` ICP iterations a level, at most ``max_points`` source
    points (the overlap thinned evenly), at most ``max_levels`` levels."""

    start_mm: float
    final_mm: float
    iterations: int = 50
    max_points: int = 8000
    shrink: float = 0.5
    rms_multiple: float = 4.0
    max_levels: int = 12


#: fewer overlap points than this at a level: the level keeps the estimate (no ICP on a handful of points)
MIN_LEVEL_POINTS = 10


def icp_coarse_to_fine(
    source_mm: ArrayLike, target: o3d.geometry.PointCloud, init: ArrayLike, schedule: FineSchedule
) -> IcpResult:
    """Point-to-plane ICP of ``source`` onto ``target`` (with normals) from ``init``, re-selecting the overlap
    as the estimate improves: at each level of ``schedule`` the overlap within the level's distance is
    extracted afresh at the current estimate (both clouds), and ICP runs on it with that correspondence
    distance. Returns the fit of the whole source at ``schedule.final_mm``."""
    S = np.asarray(source_mm, float)
    Tp = np.asarray(target.points)
    M = np.asarray(init, float).copy()
    d = max(schedule.start_mm, schedule.final_mm)
    for _ in range(schedule.max_levels):
        ov = extract_overlap(S @ M[:3, :3].T + M[:3, 3], Tp, d)
        if ov.size >= MIN_LEVEL_POINTS:
            fit = icp_point_to_plane(S[thin_evenly(ov.source_idx, schedule.max_points)],
                                     target.select_by_index(ov.target_idx.tolist()), M, d, schedule.iterations)
            M = fit.transformation
            d_next = min(d * schedule.shrink, schedule.rms_multiple * fit.rmse_mm)
        else:
            d_next = d * schedule.shrink
        if d <= schedule.final_mm:
            break
        d = max(schedule.final_mm, d_next)
    return evaluate_point_to_plane(S, target, M, schedule.final_mm)


def truncated_cost(fit: IcpResult, distance_mm: float) -> float:
    """Truncated point-to-plane cost per source point (mm^2) of a fit scored at ``distance_mm``: the squared
    residual for the inliers, ``distance_mm`` squared for the others, so a slightly smaller overlap does not
    outweigh a much closer fit. Lower is better; no inlier at all scores ``distance_mm`` squared."""
    if fit.inliers == 0:
        return distance_mm**2
    return fit.fitness * fit.rmse_mm**2 + (1.0 - fit.fitness) * distance_mm**2


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

