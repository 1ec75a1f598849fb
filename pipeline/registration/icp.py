"""Point-to-plane ICP, its coarse-to-fine schedule, its scoring and the information of a fit
(docs/registration.md, "Fine stage").

All clouds are (N, 3) arrays in millimetres; a result's ``transformation`` is ``T_target_source`` (4x4 mm,
maps source coordinates into the target's frame). The target carries normals and a KD-tree (a
:class:`TargetCloud`, made once per cloud by :func:`target_with_normals`); residuals are distances along the
target normal (mm). NumPy and SciPy only, the iteration and its stopping rule as Open3D's point-to-plane
``registration_icp`` has them (checked against it in tests/pipeline/registration/test_registration_icp.py), so the
fine stage does not import Open3D.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree
from tandemscan.pipeline.registration.normals import estimate_normals
from tandemscan.pipeline.registration.overlap import Overlap, overlap_at
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


@dataclass(frozen=True, eq=False)
class TargetCloud:
    """The target of a point-to-plane fit: points (N, 3) mm and a KD-tree of them (:func:`target_with_normals`
    makes one; prepare it once per cloud). Unit normals (PCA of the ``normal_neighbours`` nearest points) are
    computed at first use, per point, and kept: a pair's fit needs them only in its overlap. Pairs on several
    threads may share one (``online_pairs.OnlinePairs``): a lock keeps one thread at a time computing them."""

    points: np.ndarray
    tree: cKDTree
    normal_neighbours: int = 20
    known: np.ndarray = field(default=None, repr=False)     # (N, 3) normals so far, NaN where not yet computed
    _computing: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def __post_init__(self) -> None:
        if self.known is None:
            object.__setattr__(self, "known", np.full(self.points.shape, np.nan))

    def normals_at(self, indices: np.ndarray) -> np.ndarray:
        """The unit normals (len(indices), 3) of the points at ``indices``, computed where not yet known."""
        with self._computing:
            todo = np.unique(indices[np.isnan(self.known[indices, 0])])
            if len(todo):
                self.known[todo] = estimate_normals(self.points, self.normal_neighbours, self.tree, at=todo)
        return self.known[indices]

    @property
    def normals(self) -> np.ndarray:
        """The unit normals (N, 3) of all points."""
        return self.normals_at(np.arange(len(self.points)))

    def select(self, indices: np.ndarray) -> TargetCloud:
        """The target restricted to the points at ``indices``: their normals (from their neighbours in the
        whole cloud), a new KD-tree."""
        P = self.points[indices]
        return TargetCloud(P, cKDTree(P), self.normal_neighbours, self.normals_at(indices))

    def __len__(self) -> int:
        return len(self.points)


def target_with_normals(target_mm: ArrayLike | TargetCloud, normal_neighbours: int = 20) -> TargetCloud:
    """The target of a point-to-plane fit (its normals by PCA of the ``normal_neighbours`` nearest points,
    :func:`normals.estimate_normals`, computed at first use); a :class:`TargetCloud` is returned as it is."""
    if isinstance(target_mm, TargetCloud):
        return target_mm
    T = np.asarray(target_mm, float)
    if T.ndim != 2 or T.shape[1] != 3 or len(T) < normal_neighbours:
        raise RefineError(f"a point-to-plane target needs an (N, 3) cloud with N >= {normal_neighbours}; got {T.shape}")
    return TargetCloud(T, cKDTree(T), normal_neighbours)


@dataclass(frozen=True)
class Convergence:
    """When ICP stops (Open3D's ``ICPConvergenceCriteria``): after an iteration that changed the fitness by
    less than ``relative_fitness`` and the inlier RMS (point to point, mm) by less than ``relative_rmse``,
    or after ``max_iterations``; with ``stop_on_repeat`` also after an iteration that gave a correspondence
    set seen before (nearest-neighbour ICP is a discontinuous map that can cycle through a few sets,
    changing the fitness by a point and the pose by about a micrometre a step: every further iteration
    would repeat the cycle, so Open3D's rule alone runs to ``max_iterations`` there)."""

    relative_fitness: float = 1e-9
    relative_rmse: float = 1e-9
    max_iterations: int = 50
    stop_on_repeat: bool = False


def _correspondences(moved: np.ndarray, target: TargetCloud, max_distance_mm: float
                     ) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(inlier mask of ``moved``, their nearest target indices, fitness, inlier RMS point to point (mm, 0
    without inliers)): each point's nearest target point closer than ``max_distance_mm``."""
    d, idx = target.tree.query(moved, k=1, distance_upper_bound=max_distance_mm, workers=1)
    ok = d < max_distance_mm
    n = int(ok.sum())
    rmse = float(np.sqrt(np.mean(d[ok] ** 2))) if n else 0.0
    return ok, idx[ok], n / len(moved) if len(moved) else 0.0, rmse


def _euler_xyz(x: np.ndarray) -> np.ndarray:
    """4x4 of a Gauss-Newton step (rx, ry, rz rad, tx, ty, tz mm): ``Rz Ry Rx``, then the translation."""
    (cx, cy, cz), (sx, sy, sz) = np.cos(x[:3]), np.sin(x[:3])
    M = np.eye(4)
    M[:3, :3] = [[cz * cy, cz * sy * sx - sz * cx, cz * sy * cx + sz * sx],
                 [sz * cy, sz * sy * sx + cz * cx, sz * sy * cx - cz * sx],
                 [-sy, cy * sx, cy * cx]]
    M[:3, 3] = x[3:]
    return M


def _gauss_newton_step(points: np.ndarray, on_target: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """The 4x4 update minimising the linearised point-to-plane residuals ``n . (p - q)`` (one 6x6 solve;
    the identity without points, the least-norm step for a singular system)."""
    if len(points) == 0:
        return np.eye(4)
    r = np.einsum("ij,ij->i", points - on_target, normals)
    J = np.c_[np.cross(points, normals), normals]
    A, b = J.T @ J, -(J.T @ r)
    try:
        x = np.linalg.solve(A, b)
    except np.linalg.LinAlgError:
        x = np.linalg.lstsq(A, b, rcond=None)[0]
    return _euler_xyz(x)


def iterate_point_to_plane(
    source_mm: np.ndarray, target: TargetCloud, init: np.ndarray, max_distance_mm: float,
    criteria: Convergence = Convergence(),
) -> np.ndarray:
    """``T_target_source`` (4x4 mm) by point-to-plane ICP from ``init``: each iteration pairs every moved
    source point with its nearest target point closer than ``max_distance_mm`` and takes one Gauss-Newton
    step on their point-to-plane residuals, until ``criteria`` (Open3D's ``registration_icp`` semantics)."""
    M = np.asarray(init, float).copy()
    moved = source_mm @ M[:3, :3].T + M[:3, 3]
    ok, idx, fitness, rmse = _correspondences(moved, target, max_distance_mm)
    seen = {hash((ok.tobytes(), idx.tobytes()))} if criteria.stop_on_repeat else None
    for _ in range(criteria.max_iterations):
        U = _gauss_newton_step(moved[ok], target.points[idx], target.normals_at(idx))
        M = U @ M
        moved = moved @ U[:3, :3].T + U[:3, 3]
        last = fitness, rmse
        ok, idx, fitness, rmse = _correspondences(moved, target, max_distance_mm)
        if abs(last[0] - fitness) < criteria.relative_fitness and abs(last[1] - rmse) < criteria.relative_rmse:
            break
        if seen is not None:
            key = hash((ok.tobytes(), idx.tobytes()))
            if key in seen:
                break
            seen.add(key)
    return M


def icp_point_to_plane(
    source_mm: ArrayLike,
    target_mm: ArrayLike | TargetCloud,
    init: ArrayLike | None = None,
    max_distance_mm: float = 2.0,
    iterations: int = 50,
    normal_neighbours: int = 20,
    stop_on_repeat: bool = False,
) -> IcpResult:
    """Point-to-plane ICP of ``source`` onto ``target`` from ``init`` (default identity), scored at
    ``max_distance_mm`` (:func:`evaluate_point_to_plane`); ``stop_on_repeat`` as :class:`Convergence`."""
    S = np.asarray(source_mm, float)
    if S.ndim != 2 or S.shape[1] != 3:
        raise RefineError(f"ICP needs an (N, 3) source cloud; got {S.shape}")
    tgt = target_with_normals(target_mm, normal_neighbours)
    M = iterate_point_to_plane(S, tgt, np.eye(4) if init is None else np.asarray(init, float), max_distance_mm,
                           Convergence(max_iterations=iterations, stop_on_repeat=stop_on_repeat))
    return evaluate_point_to_plane(S, tgt, M, max_distance_mm)


@dataclass(frozen=True)
class FineSchedule:
    """The coarse-to-fine schedule of :func:`icp_coarse_to_fine`: the correspondence distance starts at
    ``start_mm`` and ends at ``final_mm``; after each level the next is ``shrink`` times the last, or
    ``rms_multiple`` times the level's point-to-plane RMS if that is smaller (a converged fit jumps to the
    end), never below ``final_mm``. ``iterations`` ICP iterations a level (each level stops as
    :class:`Convergence` says, ``stop_on_repeat`` included), at most ``max_points`` source points (the overlap
    thinned evenly), at most ``max_levels`` levels."""

    start_mm: float
    final_mm: float
    iterations: int = 50
    max_points: int = 8000
    shrink: float = 0.5
    rms_multiple: float = 4.0
    max_levels: int = 12
    stop_on_repeat: bool = False


#: fewer overlap points than this at a level: the level keeps the estimate (no ICP on a handful of points)
MIN_LEVEL_POINTS = 10


def icp_coarse_to_fine(
    source_mm: ArrayLike, target: TargetCloud, init: ArrayLike, schedule: FineSchedule,
    source_tree: cKDTree | None = None, first: Overlap | None = None,
) -> IcpResult:
    """Point-to-plane ICP of ``source`` onto ``target`` (with normals) from ``init``, re-selecting the overlap
    as the estimate improves: at each level of ``schedule`` the overlap within the level's distance is
    extracted afresh at the current estimate (both clouds), and ICP runs on it with that correspondence
    distance. Returns the fit of the whole source at ``schedule.final_mm``. ``source_tree``: a KD-tree of
    ``source_mm`` where the caller built one; ``first``: the overlap at ``init`` within the first level's distance
    where the caller found it."""
    S = np.asarray(source_mm, float)
    source_tree = cKDTree(S) if source_tree is None else source_tree
    M = np.asarray(init, float).copy()
    d = max(schedule.start_mm, schedule.final_mm)
    for level in range(schedule.max_levels):
        ov = first if level == 0 and first is not None else overlap_at(S, source_tree, target.points, target.tree, M, d)
        if ov.size >= MIN_LEVEL_POINTS:
            part, sub = target.select(ov.target_idx), S[thin_evenly(ov.source_idx, schedule.max_points)]
            if d <= schedule.final_mm:  # the last level: its fit on the overlap is not needed
                M = iterate_point_to_plane(sub, part, M, d, Convergence(max_iterations=schedule.iterations,
                                                                        stop_on_repeat=schedule.stop_on_repeat))
                break
            fit = icp_point_to_plane(sub, part, M, d, schedule.iterations, stop_on_repeat=schedule.stop_on_repeat)
            M = fit.transformation
            d_next = min(d * schedule.shrink, schedule.rms_multiple * fit.rmse_mm)
        elif d <= schedule.final_mm:
            break
        else:
            d_next = d * schedule.shrink
        d = max(schedule.final_mm, d_next)
    return evaluate_point_to_plane(S, target, M, schedule.final_mm)


def gate_distance(distances_mm: np.ndarray, max_distance_mm: float, sigmas: float) -> float:
    """The correspondence gate (mm) of a converged fit from its source points' distances to their nearest
    target points: the mean plus ``sigmas`` standard deviations of those within ``max_distance_mm``
    (Zhang's adaptive distance), never above ``max_distance_mm``; ``max_distance_mm`` itself with fewer
    than ``MIN_LEVEL_POINTS`` of them."""
    d = np.asarray(distances_mm, float)
    d = d[d < max_distance_mm]
    if len(d) < MIN_LEVEL_POINTS:
        return max_distance_mm
    return float(min(max_distance_mm, d.mean() + sigmas * d.std()))


def refine_at_gate(source_mm: ArrayLike, target: TargetCloud, T: ArrayLike, max_distance_mm: float,
                   sigmas: float = 3.0, iterations: int = 50, max_points: int | None = None
                   ) -> tuple[np.ndarray, float]:
    """(``T_target_source`` 4x4 mm, the gate mm): a converged fit ``T`` refined by point-to-plane ICP at its
    own correspondence gate (:func:`gate_distance` of its distances within ``max_distance_mm``) instead of
    the schedule's fixed final distance.

    The source points within ``max_distance_mm`` of the target at ``T`` (all of them: thinned evenly to the
    fine stage's 8,000, a 13,000-point overlap gave 0.005 deg instead of 0.002; or to ``max_points``) are
    matched against the whole target, correspondences re-selected at every iteration (Open3D's
    ``registration_icp``: the result is its fixed point, whichever level or stage the estimate came from),
    until :class:`Convergence`'s 1e-9, a repeated correspondence set, or ``iterations``. A fixed final
    distance sits above the tail of the true correspondences' distances, which the sampling of the surface
    sets (about the point spacing), and lets points at the overlap's border and across creases pull the fit;
    the gate follows that tail (docs/registration.md, "Fine stage")."""
    S = np.asarray(source_mm, float)
    M = np.asarray(T, float)
    d, _ = target.tree.query(S @ M[:3, :3].T + M[:3, 3], k=1, distance_upper_bound=max_distance_mm, workers=1)
    gate = gate_distance(d, max_distance_mm, sigmas)
    near = np.flatnonzero(d < max_distance_mm)
    if len(near) < MIN_LEVEL_POINTS:
        return M.copy(), gate
    return iterate_point_to_plane(S[near if max_points is None else thin_evenly(near, max_points)], target, M, gate,
                              Convergence(max_iterations=iterations, stop_on_repeat=True)), gate


def truncated_cost(fit: IcpResult, distance_mm: float) -> float:
    """Truncated point-to-plane cost per source point (mm^2) of a fit scored at ``distance_mm``: the squared
    residual for the inliers, ``distance_mm`` squared for the others, so a slightly smaller overlap does not
    outweigh a much closer fit. Lower is better; no inlier at all scores ``distance_mm`` squared."""
    if fit.inliers == 0:
        return distance_mm**2
    return fit.fitness * fit.rmse_mm**2 + (1.0 - fit.fitness) * distance_mm**2


def evaluate_point_to_plane(
    source_mm: ArrayLike, target: ArrayLike | TargetCloud, T: ArrayLike, max_distance_mm: float,
    normal_neighbours: int = 20, nearest: tuple[np.ndarray, np.ndarray] | None = None,
) -> IcpResult:
    """Score ``T_target_source`` without moving it: nearest-neighbour inliers within ``max_distance_mm``.
    ``nearest``: each source point's nearest target point at ``T`` where the caller searched them (distances mm,
    infinite beyond a bound of at least ``max_distance_mm``, and indices), not searched again."""
    S = np.asarray(source_mm, float)
    tgt = target_with_normals(target, normal_neighbours)
    M = np.asarray(T, float).copy()
    moved = S @ M[:3, :3].T + M[:3, 3]
    if nearest is None:
        ok, idx, _, _ = _correspondences(moved, tgt, max_distance_mm)
    else:
        ok = nearest[0] < max_distance_mm
        idx = nearest[1][ok]
    normals = tgt.normals_at(idx)
    r = np.einsum("ij,ij->i", moved[ok] - tgt.points[idx], normals)
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

