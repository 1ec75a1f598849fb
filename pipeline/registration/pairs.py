"""Registration of one scan pair by the configured method (docs/registration.md, "Pair registration").

Both clouds are (N, 3) arrays in millimetres in one frame (the world after the tracker stitch, or the
target's frame after an initial guess); every result is ``T_target_source`` (4x4 mm). Stages: the fine stage
from the start (``init``: coarse-to-fine point-to-plane ICP, ``icp.icp_coarse_to_fine``), and the global
stage, classical (``fpfh``: FPFH + RANSAC, ``global_registration``) or learned (``deepmerge``: the network),
each finished by the fine stage. Methods: ``icp`` (the fine stage alone), ``deepmerge`` (the network's
answer, kept only where it fits better than the start), ``deepmerge+icp``, ``fpfh+icp``, and ``auto``: the
fine stage and FPFH + RANSAC; when the two disagree, the network too; the candidate with the lowest
truncated point-to-plane cost wins, the fine stage from the start where the costs cannot tell them apart.
Every result is verified (:func:`verify`): no inliers, an infinite RMS or a cost above the start's is a
:class:`RegistrationFailed`; ``register`` (:func:`register_clouds`) also refuses a poor fit by an absolute
measure, whatever the method (:func:`fits_well`: fitness, RMS against the correspondence distance). The
network is loaded at its first use
(:class:`LazyNetwork`), so a pair that does not need it never imports PyTorch.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Protocol

import numpy as np
from scipy.spatial import cKDTree
from tandemscan.pipeline.geometry.frames import invert, rotation_angle, transform_points
from tandemscan.pipeline.parameters import FromSection
from tandemscan.pipeline.registration.global_registration import FeatureMatching, fpfh_ransac
from tandemscan.pipeline.registration.icp import (
    FineSchedule,
    IcpResult,
    TargetCloud,
    evaluate_point_to_plane,
    icp_coarse_to_fine,
    refine_at_gate,
    target_with_normals,
    truncated_cost,
)
from tandemscan.pipeline.registration.overlap import Overlap, delta_from_covariance
from tandemscan.pipeline.registration.sampling import thin_evenly

if TYPE_CHECKING:
    from tandemscan.config.models import DeepMergeConfig
    from tandemscan.pipeline.deepmerge.register import DeepMergeRegistrar

log = logging.getLogger(__name__)

#: ``register``'s final refinement gate: the mean plus this many standard deviations of the correspondence
#: distances (:func:`icp.refine_at_gate`; the job's pairs do not refine)
REFINE_SIGMAS = 3.0

#: the methods that always run the DeepMerge network (``auto`` runs it only when the others disagree)
NETWORK_METHODS = ("deepmerge", "deepmerge+icp")


@dataclass(frozen=True)
class PairCriteria(FromSection):
    """How a pair is registered and when its result is refused: ``[correction]``'s keys of the same names
    (``PairCriteria.from_section(config.correction)``; mm, deg). ``method`` (the module doc's); the fine stage's
    final correspondence distance ``icp_max_distance_mm``, ``icp_iterations`` a level and ``icp_max_points`` a
    cloud; the global stage's FPFH voxel (``global_voxel_fraction`` of the target's diagonal), RANSAC draws and
    confidence, and the distance its fine stage starts at (``global_fine_start_mm``); ``auto``'s agreement
    (``agreement_deg``, ``agreement_mm``); the verification's margin (``max_cost_increase``, :func:`verify`) and
    ``register``'s absolute gate (``register_min_fitness``, ``register_max_rms_share``, :func:`fits_well`)."""

    method: str
    icp_max_distance_mm: float
    icp_iterations: int
    icp_max_points: int
    global_voxel_fraction: float
    ransac_max_iterations: int
    ransac_confidence: float
    global_fine_start_mm: float
    agreement_deg: float
    agreement_mm: float
    max_cost_increase: float
    register_min_fitness: float
    register_max_rms_share: float


@dataclass(frozen=True)
class JobPairSettings(FromSection):
    """How the job's stitched pairs are registered (:func:`correct_pair`) and made pose-graph edges
    (``pair_stage``): ``[correction]``'s keys of the same names (mm). The pair ``criteria``, at
    ``job_pair_iterations`` a level; no edge under ``min_overlap_points``; the overlap threshold
    (:func:`pair_delta`: ``overlap_delta_mm``, else ``overlap_sigmas`` of the pair's pose uncertainty, at least
    ``overlap_min_delta_mm``); an edge's information (``edge_effective_points``, ``edge_min_eigen_ratio``)."""

    criteria: PairCriteria
    job_pair_iterations: int
    min_overlap_points: int
    overlap_delta_mm: float | None
    overlap_sigmas: float
    overlap_min_delta_mm: float
    edge_effective_points: float
    edge_min_eigen_ratio: float


class RegistrationFailed(RuntimeError):
    """A registration that must not be used: no inliers, an infinite RMS, or a fit worse than the start."""


class Registrar(Protocol):
    """Anything that registers two clouds (mm) into ``T_target_source``: the DeepMerge network."""

    def register(self, source_mm: np.ndarray, target_mm: np.ndarray) -> np.ndarray: ...


def load_registrar(network: DeepMergeConfig) -> DeepMergeRegistrar:
    """The DeepMerge network of ``[deepmerge]`` (imports PyTorch: call it only for a method that needs it)."""
    from tandemscan.pipeline.deepmerge.register import DeepMergeRegistrar

    return DeepMergeRegistrar.load(network.weights, num_points=network.num_points, rounds=network.rounds)


class LazyNetwork:
    """The network of ``[deepmerge]``, loaded (and PyTorch imported) at its first :meth:`register` (once, whichever
    of the pair stage's threads gets there first)."""

    def __init__(self, network: DeepMergeConfig) -> None:
        self.network = network
        self._registrar: DeepMergeRegistrar | None = None
        self._loading = threading.Lock()

    def __getstate__(self) -> dict:
        """Pickled as its settings only (to a Dask worker, docs/compute.md): the network loads where it is used."""
        return {"network": self.network}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["network"])

    def register(self, source_mm: np.ndarray, target_mm: np.ndarray) -> np.ndarray:
        """``T_target_source`` (4x4 mm) by the network."""
        with self._loading:
            if self._registrar is None:
                self._registrar = load_registrar(self.network)
        return self._registrar.register(source_mm, target_mm)


@dataclass(frozen=True)
class PairRegistration:
    """``T_target_source`` (4x4 mm) of a pair, its fit at the final correspondence distance, the stage whose
    candidate won (``init``, ``fpfh`` or ``deepmerge``), the truncated point-to-plane costs (mm^2 per source
    point, :func:`icp.truncated_cost`) of the result and of the start, the stages that ran, and the gate
    (mm) of the final refinement where it ran (:func:`icp.refine_at_gate`; None where it did not)."""

    transformation: np.ndarray
    fit: IcpResult
    stage: str
    cost_mm2: float
    start_cost_mm2: float
    stages_run: tuple[str, ...]
    gate_mm: float | None = None


@dataclass(frozen=True)
class PairCorrection:
    """World-frame correction ``T`` moving the source onto the target, with its fit and overlap figures."""

    transformation: np.ndarray
    fit: IcpResult
    rmse_before_mm: float
    overlap_points: int
    delta_mm: float
    centre_mm: np.ndarray
    stage: str


def keep_if_better(
    source_mm: np.ndarray, target: TargetCloud, T: np.ndarray, distance_mm: float
) -> np.ndarray:
    """``T`` when it fits the source onto the target (with normals) better than the identity (the initial
    stitch) does by the truncated point-to-plane cost at ``distance_mm`` (:func:`icp.truncated_cost`), else
    the identity."""
    def cost(M: np.ndarray) -> float:
        return truncated_cost(evaluate_point_to_plane(source_mm, target, M, distance_mm), distance_mm)

    if cost(T) > cost(np.eye(4)):
        log.debug("DeepMerge fit worse than the stitch; kept the stitch")
        return np.eye(4)
    return T


def agree(A: np.ndarray, B: np.ndarray, centre_mm: np.ndarray, cfg: PairCriteria) -> bool:
    """Whether two ``T_target_source`` estimates agree: within ``cfg.agreement_deg`` in rotation and
    ``cfg.agreement_mm`` at ``centre_mm`` (a point of the source, mm)."""
    D = A @ invert(B)
    moved = float(np.linalg.norm(transform_points(D, centre_mm[None])[0] - centre_mm))
    return np.degrees(rotation_angle(D)) <= cfg.agreement_deg and moved <= cfg.agreement_mm


def verify(result: PairRegistration, distance_mm: float, max_cost_increase: float) -> PairRegistration:
    """``result`` if it may be used, else :class:`RegistrationFailed` saying why: no inliers, an infinite
    RMS, or a truncated cost (scored at ``distance_mm``) more than ``max_cost_increase`` times
    ``distance_mm`` squared above the start's (as if that share of the points had moved out of reach)."""
    if result.fit.inliers == 0:
        raise RegistrationFailed(f"no inliers: no source point within the correspondence distance "
                                 f"(stage {result.stage})")
    if not np.isfinite(result.fit.rmse_mm):
        raise RegistrationFailed(f"infinite point-to-plane RMS (stage {result.stage})")
    if result.cost_mm2 > result.start_cost_mm2 + max_cost_increase * distance_mm**2:
        raise RegistrationFailed(f"fit worse than the start: truncated cost {result.cost_mm2:.4g} mm^2 against "
                                 f"{result.start_cost_mm2:.4g} at the start (stage {result.stage})")
    return result


@dataclass(frozen=True)
class SourceAtStitch:
    """What :func:`correct_pair` found of a source at its start (the stitch) for :func:`register_pair`: a KD-tree of
    the source points, how many points the whole source has (the fits' fitness and so their costs are shares of
    it: the points left out are out of reach of the target), the overlap at the fine stage's first distance, and
    each point's nearest target point (distances mm, infinite beyond a bound of at least that distance; indices)."""

    tree: cKDTree
    whole_points: int
    first: Overlap
    nearest: tuple[np.ndarray, np.ndarray]


def register_pair(
    source_mm: np.ndarray, target: TargetCloud, cfg: PairCriteria, network: Registrar | None,
    start_distance_mm: float, refine_sigmas: float | None = None, at_stitch: SourceAtStitch | None = None,
) -> PairRegistration:
    """``T_target_source`` of a source placed at its start (its pose so far) onto a target with normals, by
    ``cfg.method``, verified (:func:`verify`); the fine stage from the start begins at ``start_distance_mm``
    (the overlap threshold), after a global candidate at ``cfg.global_fine_start_mm``. ``auto`` without a
    ``network`` compares the fine and the classical stage only. With ``refine_sigmas`` the winner (of any
    method but ``deepmerge``, the network's own answer) is refined at its own correspondence gate
    (:func:`icp.refine_at_gate`, that many sigmas), kept unless that raises its truncated cost at the final
    distance by more than the tie margin, and the fine stage's levels stop at a repeated correspondence set
    (``FineSchedule.stop_on_repeat``); None (the job's pairs) does neither. ``at_stitch``: what
    :func:`correct_pair` found of the source at its start (:class:`SourceAtStitch`), not searched again."""
    method, final = cfg.method, cfg.icp_max_distance_mm
    S = np.asarray(source_mm, float)
    source_tree = None if at_stitch is None else at_stitch.tree

    def whole(fit: IcpResult) -> IcpResult:
        return fit if at_stitch is None else replace(fit, fitness=fit.inliers / at_stitch.whole_points)
    # the refinement settles the end, so the levels stop at a cycle; ``deepmerge`` stays the network's answer
    refining = refine_sigmas is not None and method != "deepmerge"

    def fine(M: np.ndarray, start_mm: float, first: Overlap | None = None) -> IcpResult:
        return whole(icp_coarse_to_fine(S, target, M, FineSchedule(start_mm, final, cfg.icp_iterations,
                                                                   cfg.icp_max_points, stop_on_repeat=refining),
                                        source_tree, first))

    def network_answer() -> np.ndarray:
        if network is None:
            raise ValueError(f"method {method!r} needs a DeepMerge registrar")
        return network.register(S, np.asarray(target.points))

    candidates: dict[str, IcpResult] = {}
    if method in ("icp", "auto"):
        candidates["init"] = fine(np.eye(4), start_distance_mm, None if at_stitch is None else at_stitch.first)
    if method in ("fpfh+icp", "auto"):
        matching = FeatureMatching(cfg.global_voxel_fraction, cfg.ransac_max_iterations, cfg.ransac_confidence)
        candidates["fpfh"] = fine(fpfh_ransac(S, np.asarray(target.points), matching), cfg.global_fine_start_mm)
    if method == "auto" and network is not None and not agree(
            candidates["init"].transformation, candidates["fpfh"].transformation, S.mean(axis=0), cfg):
        candidates["deepmerge"] = fine(network_answer(), cfg.global_fine_start_mm)
    if method == "deepmerge":
        candidates["deepmerge"] = whole(evaluate_point_to_plane(
            S, target, keep_if_better(S, target, network_answer(), start_distance_mm), final))
    if method == "deepmerge+icp":
        guarded = keep_if_better(S, target, network_answer(), start_distance_mm)
        candidates["deepmerge"] = fine(guarded, final)
    if not candidates:
        raise ValueError(f"unknown registration method {method!r}")
    costs = {stage: truncated_cost(fit, final) for stage, fit in candidates.items()}
    # costs closer than the verification margin cannot tell candidates apart (a slide along a smooth or
    # extruded surface fits as well): the first of them wins, so the start's own fit is kept unless a global
    # candidate fits clearly better
    tie = cfg.max_cost_increase * final**2
    stage = next(s for s, c in costs.items() if c <= min(costs.values()) + tie)
    fit, cost, gate = candidates[stage], costs[stage], None
    if refining:
        M, gate = refine_at_gate(S, target, fit.transformation, final, refine_sigmas, cfg.icp_iterations)
        refined = whole(evaluate_point_to_plane(S, target, M, final))
        if truncated_cost(refined, final) <= cost + tie:
            fit, cost = refined, truncated_cost(refined, final)
        else:
            gate = None
    start = truncated_cost(whole(evaluate_point_to_plane(S, target, np.eye(4), final,
                                                         nearest=None if at_stitch is None else at_stitch.nearest)),
                           final)
    log.debug("pair registration %s: costs %s, start %.4g mm^2, gate %s mm", method, costs, start, gate)
    return verify(PairRegistration(fit.transformation, fit, stage, cost, start, tuple(candidates), gate), final,
                  cfg.max_cost_increase)


def register_clouds(
    source_mm: np.ndarray, target_mm: np.ndarray, cfg: PairCriteria, init: np.ndarray | None = None,
    delta_mm: float = 5.0, network: Registrar | None = None, refine_sigmas: float | None = REFINE_SIGMAS,
) -> PairRegistration:
    """``T_target_source`` (mm) of any two clouds from ``init`` (default identity), verified, by ``cfg.method``,
    by the relative test (:func:`verify`) and an absolute one (:func:`fits_well`); the fine stage starts at
    ``delta_mm``, the winner is refined at its gate (``refine_sigmas``, :func:`register_pair`). Raises
    :class:`RegistrationFailed` for a result that must not be used."""
    T0 = np.eye(4) if init is None else np.asarray(init, float)
    target = target_with_normals(np.asarray(target_mm, float))
    res = register_pair(transform_points(T0, np.asarray(source_mm, float)), target, cfg, network, delta_mm,
                        refine_sigmas)
    M = res.transformation @ T0
    return fits_well(PairRegistration(M, evaluate_point_to_plane(np.asarray(source_mm, float), target, M,
                                                                 cfg.icp_max_distance_mm),
                                      res.stage, res.cost_mm2, res.start_cost_mm2, res.stages_run, res.gate_mm), cfg)


def fits_well(result: PairRegistration, cfg: PairCriteria) -> PairRegistration:
    """``result`` if its fit is good by an absolute measure, else :class:`RegistrationFailed` saying why: at
    least ``cfg.register_min_fitness`` of the source within the final correspondence distance, and a
    point-to-plane RMS of at most ``cfg.register_max_rms_share`` of it (a fit that only beats its start, a
    wrong minimum, spreads its residuals over the whole gate)."""
    gate = cfg.icp_max_distance_mm
    if result.fit.fitness < cfg.register_min_fitness:
        raise RegistrationFailed(f"poor fit: fitness {result.fit.fitness:.3f} below {cfg.register_min_fitness} "
                                 f"(stage {result.stage})")
    if result.fit.rmse_mm > cfg.register_max_rms_share * gate:
        raise RegistrationFailed(f"poor fit: point-to-plane RMS {result.fit.rmse_mm:.3f} mm above "
                                 f"{cfg.register_max_rms_share} of the {gate} mm correspondence distance "
                                 f"(stage {result.stage})")
    return result


def pair_delta(target_W: np.ndarray, cfg: JobPairSettings, pair_covariance: np.ndarray | None) -> float:
    """The overlap threshold (mm) of a stitched pair: configured, or from the pair's pose covariance."""
    if cfg.overlap_delta_mm is not None:
        return cfg.overlap_delta_mm
    if pair_covariance is None:
        raise ValueError("overlap_delta_mm is not configured and no pair covariance was given")
    lever = 0.5 * float(np.linalg.norm(np.ptp(target_W, axis=0)))
    return delta_from_covariance(pair_covariance, lever, cfg.overlap_sigmas, cfg.overlap_min_delta_mm)


def correct_pair(
    source_W: np.ndarray, target: TargetCloud, cfg: JobPairSettings, network: Registrar | None,
    pair_covariance: np.ndarray | None = None,
) -> PairCorrection | None:
    """Correct a stitched pair (the source in the world, mm; the target with normals, world); None when the
    overlap is below ``min_overlap_points``; :class:`RegistrationFailed` for a result that must not be used.

    The whole clouds are registered, the overlap re-selected from them at each level as the fit converges
    (registering only the overlap at the stitch, or onto only the target's overlap, measured worse on the
    simulated job, docs/registration.md); the edge's fit is scored on the source overlap at the stitch,
    thinned evenly to ``icp_max_points``. The fine stage runs ``cfg.job_pair_iterations`` a level (from the
    tracker stitch more only slide along smooth overlaps, docs/compute.md). Each cloud is searched once at the
    stitch (:class:`SourceAtStitch`).

    With ``method = "icp"`` only the source points within :data:`REACH_MULTIPLE` times the largest correspondence
    distance of the target at the stitch take part: the overlaps, fits and scores are those of the whole source
    while no point left out comes within that distance of the target, which is checked on the result
    (:func:`stays_out_of_reach`); where one may have, or where the fit was refused, the pair is registered again
    with the whole source.
    """
    target_W = np.asarray(target.points)
    delta = pair_delta(target_W, cfg, pair_covariance)
    largest = max(delta, cfg.criteria.icp_max_distance_mm)
    if cfg.criteria.method == "icp":
        reach = REACH_MULTIPLE * largest
        d, idx = target.tree.query(source_W, k=1, distance_upper_bound=reach, workers=1)
        near = np.flatnonzero(d < reach)
        try:
            pc = _correct_from_stitch(source_W[near], len(source_W), (d[near], idx[near]), target, cfg, network,
                                      delta)
        except RegistrationFailed:  # decided on the whole source (a refused fit may have moved it beyond reach)
            pc = None
        else:
            if pc is None or stays_out_of_reach(pc.transformation, source_W, target_W, largest, reach):
                return pc
        log.debug("pair correction: registered again with the whole source")
    nearest = target.tree.query(source_W, k=1, distance_upper_bound=largest, workers=1)
    return _correct_from_stitch(source_W, len(source_W), nearest, target, cfg, network, delta)


#: :func:`correct_pair` registers the source points within this many times the pair's largest correspondence
#: distance of the target at the stitch
REACH_MULTIPLE = 2.0


def box_move_mm(T: np.ndarray, low: np.ndarray, high: np.ndarray) -> float:
    """The largest distance (mm) by which ``T`` (4x4 mm) moves a point of the box from ``low`` to ``high`` (mm):
    at one of its corners (the move is affine in the point, its length convex)."""
    corners = np.array([[(low, high)[(k >> a) & 1][a] for a in range(3)] for k in range(8)], float)
    return float(np.linalg.norm(transform_points(T, corners) - corners, axis=1).max())


def stays_out_of_reach(T: np.ndarray, source_W: np.ndarray, target_W: np.ndarray, distance_mm: float,
                       reach_mm: float) -> bool:
    """Whether ``T`` (4x4 mm) brings no source point that is farther than ``reach_mm`` from the target within
    ``distance_mm`` of it (all mm, W). Such a point lies in the source's bounding box, within ``distance_mm`` plus
    its move of the target's bounding box, and moves at least ``reach_mm - distance_mm``: its move is bounded by
    that at the corners of the boxes' common part, which each bound narrows again."""
    low, high = source_W.min(axis=0), source_W.max(axis=0)
    t_low, t_high = target_W.min(axis=0), target_W.max(axis=0)
    move = box_move_mm(T, low, high)
    for _ in range(3):
        lo, hi = np.maximum(low, t_low - distance_mm - move), np.minimum(high, t_high + distance_mm + move)
        if np.any(lo > hi):
            return True
        move = box_move_mm(T, lo, hi)
    return move <= reach_mm - distance_mm


def _correct_from_stitch(source_W: np.ndarray, whole_points: int, nearest: tuple[np.ndarray, np.ndarray],
                         target: TargetCloud, cfg: JobPairSettings, network: Registrar | None, delta_mm: float
                         ) -> PairCorrection | None:
    """:func:`correct_pair` on ``source_W``, the points of a source of ``whole_points`` points that can reach the
    target (all of them, or those :func:`correct_pair` kept) and their ``nearest`` target points at the stitch
    (searched within at least the largest correspondence distance), at the overlap threshold ``delta_mm``."""
    if len(source_W) < cfg.min_overlap_points:
        return None
    largest = max(delta_mm, cfg.criteria.icp_max_distance_mm)
    source_tree = cKDTree(source_W)
    d_t, _ = source_tree.query(target.points, k=1, distance_upper_bound=largest, workers=1)
    d_s = nearest[0]
    ov = Overlap(np.flatnonzero(d_s < delta_mm), np.flatnonzero(d_t < delta_mm), delta_mm)
    if ov.size < cfg.min_overlap_points:
        return None
    first = Overlap(np.flatnonzero(d_s < largest), np.flatnonzero(d_t < largest), largest)
    # the job's pairs do not refine at a gate (no refine_sigmas), so icp_iterations is the fine stage's alone
    criteria = replace(cfg.criteria, icp_iterations=cfg.job_pair_iterations)
    reg = register_pair(source_W, target, criteria, network, delta_mm,
                        at_stitch=SourceAtStitch(source_tree, whole_points, first, nearest))
    thin = thin_evenly(ov.source_idx, criteria.icp_max_points)
    S = source_W[thin]
    fit = evaluate_point_to_plane(S, target, reg.transformation, criteria.icp_max_distance_mm)
    before = evaluate_point_to_plane(S, target, np.eye(4), criteria.icp_max_distance_mm,
                                     nearest=(d_s[thin], nearest[1][thin]))
    return PairCorrection(reg.transformation, fit, before.rmse_mm, ov.size, delta_mm,
                          target.points[ov.target_idx].mean(axis=0), reg.stage)
