"""Stitching correction of a whole job: overlapping scan pairs -> corrections -> pose graph (DESIGN.md 5.5-5.6).

Input: every scan's points in its scanner frame S, its tracker-stitched pose ``T_W_S`` with covariance and
its tracker station. For each overlapping pair the overlap (``overlap``) is registered by the configured
method (DeepMerge, point-to-plane ICP, or DeepMerge then ICP), each correction becomes a pose-graph edge,
and ``refine.refine_poses`` spreads the corrections over all scans.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from tandemscan.config.models import DeepMergeConfig
from tandemscan.pipeline.deepmerge.overlap import (
    delta_from_covariance,
    extract_overlap,
    overlapping_pairs,
    relative_covariance,
    thin_evenly,
)
from tandemscan.pipeline.deepmerge.register import DeepMergeRegistrar, voxel_downsample
from tandemscan.pipeline.frames import invert, pose_error, transform_points
from tandemscan.pipeline.refine import (
    IcpResult,
    MountEstimate,
    MountPrior,
    PairEdge,
    ScanPrior,
    TransferPrior,
    constrained_edge,
    evaluate_point_to_plane,
    icp_point_to_plane,
    point_to_plane_information,
    refine_poses,
    target_with_normals,
)
from tandemscan.pipeline.uncertainty import covariance_about

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PairCorrection:
    """World-frame correction ``T`` moving the source onto the target, with its fit and overlap figures."""

    transformation: np.ndarray
    fit: IcpResult
    rmse_before_mm: float
    overlap_points: int
    delta_mm: float
    centre_mm: np.ndarray


def keep_if_better(
    source_mm: np.ndarray, target: o3d.geometry.PointCloud, T: np.ndarray, distance_mm: float
) -> np.ndarray:
    """``T`` when it fits the source onto the target (with normals) better than the identity (the initial
    stitch) does, else the identity.

    The score is the truncated point-to-plane cost per source point: squared distance for the points with a
    correspondence within ``distance_mm``, ``distance_mm`` squared for the others, so a slightly smaller
    overlap does not outweigh a much closer fit.
    """
    def cost(M: np.ndarray) -> float:
        fit = evaluate_point_to_plane(source_mm, target, M, distance_mm)
        return fit.fitness * fit.rmse_mm**2 + (1.0 - fit.fitness) * distance_mm**2

    if cost(T) > cost(np.eye(4)):
        log.debug("DeepMerge fit worse than the stitch; kept the stitch")
        return np.eye(4)
    return T


def register_overlap(
    source_mm: np.ndarray, target_mm: np.ndarray | o3d.geometry.PointCloud, method: str, cfg: DeepMergeConfig,
    registrar: DeepMergeRegistrar | None, coarse_distance_mm: float,
) -> np.ndarray:
    """``T_target_source`` of two overlap clouds by ``method`` (the target may come with its normals).

    ``icp`` runs point-to-plane ICP coarse (``coarse_distance_mm``, the overlap threshold) then fine
    (``cfg.icp_max_distance_mm``), the fair baseline; ``deepmerge`` keeps the network's answer only where
    it fits the overlap better than the initial stitch (:func:`keep_if_better`); ``deepmerge+icp`` runs the
    fine ICP after that.
    """
    T = np.eye(4)
    if method in ("deepmerge", "deepmerge+icp"):
        if registrar is None:
            raise ValueError(f"method {method!r} needs a DeepMerge registrar")
        target_mm = target_with_normals(target_mm)
        T = keep_if_better(source_mm, target_mm, registrar.register(source_mm, np.asarray(target_mm.points)),
                           coarse_distance_mm)
    if method == "icp":
        T = icp_point_to_plane(source_mm, target_mm, T, max(coarse_distance_mm, cfg.icp_max_distance_mm),
                               cfg.icp_iterations).transformation
    if method in ("icp", "deepmerge+icp"):
        T = icp_point_to_plane(source_mm, target_mm, T, cfg.icp_max_distance_mm, cfg.icp_iterations).transformation
    return T


def register_clouds(
    source_mm: np.ndarray, target_mm: np.ndarray, cfg: DeepMergeConfig, method: str | None = None,
    init: np.ndarray | None = None, delta_mm: float = 5.0, registrar: DeepMergeRegistrar | None = None,
) -> tuple[np.ndarray, IcpResult]:
    """``T_target_source`` (mm) of any two clouds from ``init`` and its fit (at ``cfg.icp_max_distance_mm``).

    The overlap within ``delta_mm`` after ``init`` is registered; with fewer than ``cfg.min_overlap_points``
    there, the whole clouds are.
    """
    method = method or cfg.method
    if method != "icp" and registrar is None:
        registrar = DeepMergeRegistrar.load(cfg.weights, num_points=cfg.num_points)
    T0 = np.eye(4) if init is None else np.asarray(init, float)
    S, T = transform_points(T0, np.asarray(source_mm, float)), np.asarray(target_mm, float)
    ov = extract_overlap(S, T, delta_mm)
    if ov.size >= cfg.min_overlap_points:
        S_ov, T_ov = S[ov.source_idx], T[ov.target_idx]
    else:
        S_ov, T_ov = S, T
    M = register_overlap(S_ov, T_ov, method, cfg, registrar, delta_mm) @ T0
    return M, evaluate_point_to_plane(np.asarray(source_mm, float), T, M, cfg.icp_max_distance_mm)


def correct_pair(
    source_W: np.ndarray, target_W: np.ndarray, cfg: DeepMergeConfig, registrar: DeepMergeRegistrar | None,
    pair_covariance: np.ndarray | None = None,
) -> PairCorrection | None:
    """Correct a stitched pair (both in the world, mm); None when the overlap is below ``min_overlap_points``.

    A source overlap larger than ``cfg.icp_max_points`` is thinned evenly before registration (the target
    keeps every point, so its normals and the point-to-plane distances stay as fine as the scan).
    """
    if cfg.overlap_delta_mm is not None:
        delta = cfg.overlap_delta_mm
    else:
        if pair_covariance is None:
            raise ValueError("overlap_delta_mm is not configured and no pair covariance was given")
        lever = 0.5 * float(np.linalg.norm(np.ptp(target_W, axis=0)))
        delta = delta_from_covariance(pair_covariance, lever, cfg.overlap_sigmas, cfg.overlap_min_delta_mm)
    ov = extract_overlap(source_W, target_W, delta)
    if ov.size < cfg.min_overlap_points:
        return None
    S, T = source_W[thin_evenly(ov.source_idx, cfg.icp_max_points)], target_W[ov.target_idx]
    tgt = target_with_normals(T)
    M = register_overlap(S, tgt, cfg.method, cfg, registrar, delta)
    fit = evaluate_point_to_plane(S, tgt, M, cfg.icp_max_distance_mm)
    before = evaluate_point_to_plane(S, tgt, np.eye(4), cfg.icp_max_distance_mm)
    return PairCorrection(M, fit, before.rmse_mm, ov.size, delta, T.mean(axis=0))


@dataclass(frozen=True)
class StitchedScan:
    """One scan: points in the scanner frame (mm), tracker pose ``T_W_S``, its covariance, its station."""

    points_S: np.ndarray
    T_W_S: np.ndarray
    covariance: np.ndarray
    station: int = 0


@dataclass
class CorrectionResult:
    """Refined poses and the figures a report needs (mm, deg); the shared mount correction if estimated."""

    poses: list[np.ndarray]
    edges: list[tuple[int, int, PairCorrection]] = field(default_factory=list)
    report: dict = field(default_factory=dict)
    mount: MountEstimate | None = None


def _overlap_rms(clouds: list[np.ndarray], edges, poses_before, poses_after, cfg) -> tuple[float, float]:
    """Median over edges of the point-to-plane RMS (mm) of the overlaps, with the poses before and after."""
    out = []
    targets = {i: target_with_normals(clouds[i]) for i in {e[0] for e in edges}}
    for poses in (poses_before, poses_after):
        vals = []
        for i, j, _ in edges:
            Tij = invert(poses[i]) @ poses[j]
            vals.append(evaluate_point_to_plane(clouds[j], targets[i], Tij, cfg.icp_max_distance_mm).rmse_mm)
        out.append(float(np.median(vals)) if vals else float("nan"))
    return out[0], out[1]


def _edge(i: int, j: int, pc: PairCorrection, cfg: DeepMergeConfig) -> PairEdge:
    """Pose-graph edge of a pair correction, keeping only the directions the overlap constrains."""
    info = point_to_plane_information(pc.fit.points_mm, pc.fit.normals, pc.centre_mm, max(pc.fit.rmse_mm, 0.005),
                                      cfg.edge_effective_points)
    size = float(np.sqrt(((pc.fit.points_mm - pc.centre_mm) ** 2).sum(axis=1).mean()))
    T, info = constrained_edge(pc.transformation, info, pc.centre_mm, max(size, 1.0), cfg.edge_min_eigen_ratio)
    return PairEdge(i, j, T, info, pc.centre_mm)


def correct_scans(
    scans: Sequence[StitchedScan], cfg: DeepMergeConfig, registrar: DeepMergeRegistrar | None = None,
    transfers: Sequence[TransferPrior] = (), voxel_mm: float = 1.0, mount_prior: MountPrior | None = None,
) -> CorrectionResult:
    """Correct every overlapping pair and refine all poses; ``voxel_mm`` thins the scans first.

    ``transfers`` (one per tracker station after the first, see ``refine.refine_poses``) let the graph
    remove the drift of the coordinate transfers and widen the overlap threshold of pairs across stations;
    ``mount_prior`` makes the graph estimate the shared scanner-mount correction too (``refine.MountPrior``).
    """
    if cfg.method != "icp" and registrar is None:
        registrar = DeepMergeRegistrar.load(cfg.weights, num_points=cfg.num_points)
    local = [voxel_downsample(np.asarray(s.points_S, float), voxel_mm) for s in scans]
    world = [transform_points(s.T_W_S, P) for s, P in zip(scans, local, strict=True)]
    edges: list[tuple[int, int, PairCorrection]] = []
    for i, j in overlapping_pairs(world, [s.station for s in scans], cfg.pair_cell_mm, cfg.max_partners_per_scan):
        cov = relative_covariance(scans[i].covariance, scans[j].covariance)
        low, high = sorted((scans[i].station, scans[j].station))
        for t in transfers:                          # the drift between the two stations, at the target scan
            if low < t.station <= high:
                cov = cov + covariance_about(t.covariance, t.centre_mm, scans[i].T_W_S[:3, 3])
        pc = correct_pair(world[j], world[i], cfg, registrar, cov)
        if pc is not None:
            edges.append((i, j, pc))
    graph_edges = [_edge(i, j, pc, cfg) for i, j, pc in edges if pc.fit.inliers >= 6]
    priors = [ScanPrior(s.T_W_S, s.covariance, s.station) for s in scans]
    res = refine_poses(priors, graph_edges, transfers, mount_prior)
    before = [s.T_W_S for s in scans]
    rms_b, rms_a = _overlap_rms(local, edges, before, res.poses, cfg)
    moves = [pose_error(a, b) for a, b in zip(res.poses, before, strict=True)]
    report = {
        "method": cfg.method,
        "scans": len(scans),
        "pairs": len(edges),
        "overlap_rms_mm_median_before": rms_b,
        "overlap_rms_mm_median_after": rms_a,
        "pose_change_mm_median": float(np.median([m[0] for m in moves])) if moves else 0.0,
        "pose_change_deg_median": float(np.degrees(np.median([m[1] for m in moves]))) if moves else 0.0,
        "graph_cost_before": res.cost_before,
        "graph_cost_after": res.cost_after,
    }
    log.info("correction: %d scans, %d pairs, overlap RMS %.4f -> %.4f mm", len(scans), len(edges), rms_b, rms_a)
    return CorrectionResult(res.poses, edges, report, res.mount)
