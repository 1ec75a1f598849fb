"""Registration of one scan pair by the configured method (docs/registration.md, "Pair registration").

Both clouds are (N, 3) arrays in millimetres in one frame (the world after the tracker stitch, or the
target's frame after an initial guess); every result is ``T_target_source`` (4x4 mm). Methods: ``icp``
(point-to-plane, coarse at the overlap threshold then fine), ``deepmerge`` (the network, kept only where it
fits better than the start), ``deepmerge+icp`` (that, then the fine ICP). The network is loaded only for the
methods that use it (``load_registrar``), so the ICP path never imports PyTorch.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import open3d as o3d
from tandemscan.config.models import CorrectionConfig, DeepMergeConfig
from tandemscan.pipeline.frames import transform_points
from tandemscan.pipeline.registration.icp import (
    IcpResult,
    evaluate_point_to_plane,
    icp_point_to_plane,
    target_with_normals,
)
from tandemscan.pipeline.registration.overlap import delta_from_covariance, extract_overlap
from tandemscan.pipeline.registration.sampling import thin_evenly

if TYPE_CHECKING:
    from tandemscan.pipeline.deepmerge.register import DeepMergeRegistrar

log = logging.getLogger(__name__)

#: the methods that run the DeepMerge network
NETWORK_METHODS = ("deepmerge", "deepmerge+icp")


def load_registrar(network: DeepMergeConfig) -> DeepMergeRegistrar:
    """The DeepMerge network of ``[deepmerge]`` (imports PyTorch: call it only for a method that needs it)."""
    from tandemscan.pipeline.deepmerge.register import DeepMergeRegistrar

    return DeepMergeRegistrar.load(network.weights, num_points=network.num_points)


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
    source_mm: np.ndarray, target_mm: np.ndarray | o3d.geometry.PointCloud, method: str, cfg: CorrectionConfig,
    registrar: DeepMergeRegistrar | None, coarse_distance_mm: float,
) -> np.ndarray:
    """``T_target_source`` of two overlap clouds by ``method`` (the target may come with its normals).

    ``icp`` runs point-to-plane ICP coarse (``coarse_distance_mm``, the overlap threshold) then fine
    (``cfg.icp_max_distance_mm``), the fair baseline; ``deepmerge`` keeps the network's answer only where
    it fits the overlap better than the initial stitch (:func:`keep_if_better`); ``deepmerge+icp`` runs the
    fine ICP after that.
    """
    T = np.eye(4)
    if method in NETWORK_METHODS:
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
    source_mm: np.ndarray, target_mm: np.ndarray, cfg: CorrectionConfig, method: str | None = None,
    init: np.ndarray | None = None, delta_mm: float = 5.0, registrar: DeepMergeRegistrar | None = None,
) -> tuple[np.ndarray, IcpResult]:
    """``T_target_source`` (mm) of any two clouds from ``init`` and its fit (at ``cfg.icp_max_distance_mm``);
    the network methods need ``registrar`` (:func:`load_registrar`).

    The overlap within ``delta_mm`` after ``init`` is registered; with fewer than ``cfg.min_overlap_points``
    there, the whole clouds are.
    """
    method = method or cfg.method
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
    source_W: np.ndarray, target_W: np.ndarray, cfg: CorrectionConfig, registrar: DeepMergeRegistrar | None,
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

