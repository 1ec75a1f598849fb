"""Stitching correction of a whole job: overlapping scan pairs -> corrections -> pose graph
(docs/correction.md).

Input: every scan's points in its scanner frame S, its tracker-stitched pose ``T_W_S`` with covariance and
its tracker station. For each overlapping pair (``overlap.overlapping_pairs``) the overlap is registered by
the configured method (``pairs.correct_pair``), each correction becomes a pose-graph edge, and
``pose_graph.refine_poses`` spreads the corrections over all scans; with ``[correction] joint`` the poses are
instead refined jointly on the overlap points from the tracker poses (``joint.refine_jointly``), and the graph is
not solved.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import logging
import shutil
import time
from collections import Counter
from collections.abc import Callable, Mapping, MutableMapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tandemscan.pipeline.compute import ComputeBackend, LocalBackend, StoredResults
from tandemscan.pipeline.geometry.frames import invert, pose_error, transform_points
from tandemscan.pipeline.geometry.uncertainty import covariance_about
from tandemscan.pipeline.parameters import FromSection
from tandemscan.pipeline.registration.icp import evaluate_point_to_plane, target_with_normals
from tandemscan.pipeline.registration.joint import (
    Association,
    JointResult,
    JointScan,
    JointSettings,
    StoredJointScan,
    chain_covariance,
    loaded_scan,
    refine_jointly,
)
from tandemscan.pipeline.registration.mount_unknown import MountEstimate, MountPrior
from tandemscan.pipeline.registration.overlap import (
    occupied_cells,
    relative_covariance,
    select_pairs,
    shared_cells,
)
from tandemscan.pipeline.registration.pair_stage import (
    HeldScans,
    PairOutcome,
    ScanRef,
    StoredScans,
    TargetPairs,
    register_units,
)
from tandemscan.pipeline.registration.pairs import NETWORK_METHODS, JobPairSettings, Registrar
from tandemscan.pipeline.registration.parallel import pair_threads
from tandemscan.pipeline.registration.pose_covariance import PoseCovariance
from tandemscan.pipeline.registration.pose_graph import (
    PairEdge,
    ScanPrior,
    TransferPrior,
    refine_poses,
)
from tandemscan.pipeline.registration.sampling import thin_evenly, voxel_centroids, voxel_downsample
from tandemscan.pipeline.stitching.tiles import ScanReach

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CorrectionSettings(FromSection):
    """The whole-job correction's parameters: ``[correction]``'s keys of the same names
    (``CorrectionSettings.from_section(config.correction)``, built once where the job starts; mm). Whether it
    runs (``enabled``); the pairs (``pairs``: how each is registered), found on a grid of ``pair_cell_mm`` with
    at most ``max_partners_per_scan`` a scan (the pose graph's and the overlap RMS's), of which with ``joint``
    only ``check_partners_per_scan`` a scan are registered (:attr:`registered_partners`); with ``joint`` the
    joint refinement (``joint_refinement``) on scans thinned to ``joint_voxel_mm`` with at most
    ``joint_max_partners_per_scan`` partners, else the pose graph."""

    enabled: bool
    pairs: JobPairSettings
    pair_cell_mm: float
    max_partners_per_scan: int
    check_partners_per_scan: int
    joint: bool
    joint_refinement: JointSettings
    joint_voxel_mm: float
    joint_max_partners_per_scan: int

    @property
    def method(self) -> str:
        """The pair registration method (``pairs.criteria.method``)."""
        return self.pairs.criteria.method

    @property
    def registered_partners(self) -> int:
        """Partners a scan is registered with (``overlap.overlapping_pairs``' ``max_partners``; 0: no pair is
        registered): the pose graph's ``max_partners_per_scan``, or with ``joint``, which takes no pose from the
        pairs (it starts from the tracker poses), ``check_partners_per_scan``: the pairs are then a check only
        (docs/correction.md, "Which pairs are registered")."""
        return self.check_partners_per_scan if self.joint else self.max_partners_per_scan


@dataclass(frozen=True)
class StitchedScan:
    """One scan: points in the scanner frame (mm; None where the correction is given a scan store: they are read
    where they are needed, :func:`correct_scans`), tracker pose ``T_W_S``, its covariance, its station, and its raw
    scan file relative to the job's scan store (``pair_stage.StoredScans``; empty where it has none)."""

    points_S: np.ndarray | None
    T_W_S: np.ndarray
    covariance: np.ndarray
    station: int = 0
    file: str = ""


@dataclass(frozen=True)
class StitchedJob:
    """What the tracker stitch of a job gives the correction: its ``scans``; the prior of each coordinate transfer
    (``transfers``, one per tracker station after the first, ``pose_graph.TransferPrior``: the refinement removes
    their drift, and pairs across stations get a wider overlap threshold); the prior of the shared scanner-mount
    correction (``mount_prior``, ``mount_unknown.MountPrior``; None: not estimated); and the voxel (mm) the scans
    are thinned to first (``voxel_mm``, the map's, ``[job] voxel_mm``)."""

    scans: Sequence[StitchedScan]
    transfers: Sequence[TransferPrior] = ()
    mount_prior: MountPrior | None = None
    voxel_mm: float = 1.0


@dataclass(frozen=True)
class OnlineWork:
    """What a job computed while it measured (``online_pairs.OnlinePairs``), for :func:`correct_scans`: pair
    outcomes by :func:`pair_key`, scans prepared for the joint refinement by :func:`joint_scan_key` (taken out as
    the refinement takes them) and their pairs' nearest neighbours by :func:`association_key`; the CPU seconds the
    pairs' registrations took (``pair_cpu_s``, their threads' own, for the report's figure a pair)."""

    pairs: dict[str, PairOutcome]
    joint_scans: dict[str, JointScan]
    associations: dict[str, Association]
    pair_cpu_s: float = 0.0
    #: keys of the pairs still being registered when this was handed over (``OnlinePairs.joint_work``): with the
    #: joint refinement :func:`correct_scans` leaves them to :func:`complete_pair_checks` (:class:`PairChecks`)
    pending: frozenset[str] = frozenset()


@dataclass(frozen=True)
class PendingPair:
    """A check pair still registering where the job measured: its place in the job's pairs (``slot``), both scans
    by reference (target, source), its relative pose covariance and its cache key (:func:`pair_key`)."""

    slot: int
    target: ScanRef
    source: ScanRef
    covariance: np.ndarray
    key: str


@dataclass(frozen=True)
class PairChecks:
    """The check pairs of a job whose poses the joint refinement gave while some of its pairs were still registering
    (``OnlineWork.pending``): every pair registered, in order, with its outcome where known (None where pending), the
    pending ones (:class:`PendingPair`), how many outcomes came from the work done while measuring, and the CPU
    seconds a pair took there so far. :func:`complete_pair_checks` gives the report's pair figures."""

    outcomes: tuple[tuple[int, int, PairOutcome | None], ...]
    pending: tuple[PendingPair, ...]
    cached: int
    cpu_s_a_pair: float | None


@dataclass
class CorrectionResult:
    """Refined poses and the figures a report needs (mm, deg); the shared mount correction if estimated."""

    poses: list[np.ndarray]
    edges: list[tuple[int, int, PairOutcome]] = field(default_factory=list)
    report: dict = field(default_factory=dict)
    mount: MountEstimate | None = None
    pose_covariance: PoseCovariance | None = None  # the scans' errors jointly (``pose_covariance``)
    reaches: tuple[ScanReach, ...] = ()  # each scan's bound of its x at any pose (``tiles.ScanReach``)
    checks: PairChecks | None = None  # pairs still registering: ``report`` has no pair figures yet


class _Clock:
    """Wall seconds of consecutive stages (``lap(name)`` ends the stage begun at the last lap)."""

    def __init__(self) -> None:
        self.laps: dict[str, float] = {}
        self._t = time.perf_counter()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.laps[name] = round(now - self._t, 3)
        self._t = now


#: points of a source scan, evenly spread, on which the report's overlap RMS is evaluated: a median over the
#: job's pairs of RMS values from hundreds of inliers each is a stable figure; more only costs time
OVERLAP_RMS_POINTS = 2000
#: target scans, evenly spread over the job's, whose pairs the report's overlap RMS is evaluated on: each
#: target's normals cost as much as its pairs' evaluation, and a median over a few hundred pairs (about four
#: a target) is as stable as one over all of them (a whole part: 1,460 pairs, 6.3 s on two cores)
OVERLAP_RMS_TARGETS = 64


@dataclass(frozen=True)
class OverlapRmsUnit:
    """A unit of the report's overlap RMS (:func:`_overlap_rms`): a target scan, its partners (sources), and each
    source's pose relative to the target (``T_i_j``, 4x4, mm) before and after the correction."""

    target: ScanRef
    sources: tuple[ScanRef, ...]
    before: tuple[np.ndarray, ...]
    after: tuple[np.ndarray, ...]

    def key(self, voxel_mm: float, distance_mm: float) -> str:
        """The unit's name: its scans' files and every pose it depends on, the voxel and the distance (mm)."""
        h = hashlib.blake2b(digest_size=16)
        for ref in (self.target, *self.sources):
            h.update(ref.file.encode())
        h.update(np.ascontiguousarray(np.stack([*self.before, *self.after]), np.float64).tobytes())
        h.update(np.float64([voxel_mm, distance_mm]).tobytes())
        return f"overlap-rms-{h.hexdigest()}"


def overlap_rms_of_target(unit: OverlapRmsUnit, clouds: Callable[[ScanRef], np.ndarray], distance_mm: float
                          ) -> list[tuple[float, float]]:
    """The point-to-plane RMS (mm) of each source of ``unit`` on its target, before and after: the target's normals
    once, each source evaluated on at most :data:`OVERLAP_RMS_POINTS` of its points, evenly spread, scored within
    ``distance_mm``; ``clouds`` gives a scan's thinned points (S, mm) by reference."""
    target = target_with_normals(clouds(unit.target))
    out = []
    for ref, before, after in zip(unit.sources, unit.before, unit.after, strict=True):
        points = clouds(ref)
        source = points[thin_evenly(np.arange(len(points)), OVERLAP_RMS_POINTS)]
        out.append(tuple(evaluate_point_to_plane(source, target, T, distance_mm).rmse_mm for T in (before, after)))
    return out


def _overlap_rms(units: Sequence[OverlapRmsUnit], clouds: Callable[[ScanRef], np.ndarray], distance_mm: float,
                 voxel_mm: float, backend: ComputeBackend) -> tuple[float, float]:
    """Median over the units' pairs (:func:`_overlap_rms_units`) of the point-to-plane RMS (mm) of the overlaps,
    with the poses before and after (:func:`overlap_rms_of_target` on ``backend``, the scans from ``clouds``)."""
    fn = functools.partial(overlap_rms_of_target, clouds=clouds, distance_mm=distance_mm)
    done = backend.map(fn, units, [u.key(voxel_mm, distance_mm) for u in units])
    vals = np.array([v for group in done for v in group]).reshape(-1, 2)
    if not len(vals):
        return float("nan"), float("nan")
    return float(np.median(vals[:, 0])), float(np.median(vals[:, 1]))


def _overlap_rms_units(scans: Sequence[StitchedScan], pairs: Sequence[tuple[int, int]], poses_before, poses_after
                       ) -> list[OverlapRmsUnit]:
    """The overlap RMS's units: the ``pairs`` (target, source) of at most :data:`OVERLAP_RMS_TARGETS` target scans,
    evenly spread over the job's, one unit a target."""
    by_target: dict[int, list[int]] = {}
    for i, j in pairs:
        by_target.setdefault(i, []).append(j)

    def ref(k: int) -> ScanRef:
        return ScanRef(k, scans[k].file, scans[k].T_W_S)

    return [OverlapRmsUnit(ref(i), tuple(ref(j) for j in by_target[i]),
                           *(tuple(invert(poses[i]) @ poses[j] for j in by_target[i])
                             for poses in (poses_before, poses_after)))
            for i in (int(i) for i in thin_evenly(np.array(sorted(by_target)), OVERLAP_RMS_TARGETS))]


def pair_covariance(scan_i: StitchedScan, scan_j: StitchedScan, transfers: Sequence[TransferPrior]) -> np.ndarray:
    """6x6 covariance (mm^2, rad^2) of the relative pose of two stitched scans: both tracker poses and the drift
    of every coordinate transfer between their stations, about the target scan ``i``'s origin."""
    cov = relative_covariance(scan_i.covariance, scan_j.covariance)
    low, high = sorted((scan_i.station, scan_j.station))
    for t in transfers:
        if low < t.station <= high:
            cov = cov + covariance_about(t.covariance, t.centre_mm, scan_i.T_W_S[:3, 3])
    return cov


def cloud_digest(world_mm: np.ndarray) -> bytes:
    """A digest of a scan's thinned world cloud (mm): a pair's cached outcome is reused only for the same two
    clouds (so the same poses and points)."""
    return hashlib.blake2b(np.ascontiguousarray(world_mm, np.float64).tobytes(), digest_size=16).digest()


def pair_key(digest_i: bytes, digest_j: bytes, covariance: np.ndarray, cfg: JobPairSettings) -> str:
    """The cache key of pair ``(i, j)``: everything its registration depends on (clouds, covariance, settings)."""
    h = hashlib.blake2b(digest_i + digest_j, digest_size=16)
    h.update(np.ascontiguousarray(covariance, np.float64).tobytes())
    h.update(repr(cfg).encode())
    return h.hexdigest()


def joint_scan(points_S: np.ndarray, voxel_mm: float) -> JointScan:
    """A scan as the joint refinement takes it: its points (S, mm; as the end of the job loads them) thinned to
    ``voxel_mm`` (``[correction] joint_voxel_mm``), with normals and how many of those points each thinned one
    averages (``joint.JointScan.from_points``)."""
    centroids, counts = voxel_centroids(np.asarray(points_S, float), voxel_mm)
    return JointScan.from_points(centroids, counts=counts)


def joint_scan_key(points_S: np.ndarray, voxel_mm: float) -> str:
    """The cache key of :func:`joint_scan`: the points themselves and the joint voxel (mm)."""
    h = hashlib.blake2b(cloud_digest(points_S), digest_size=16)
    h.update(np.float64(voxel_mm).tobytes())
    return h.hexdigest()


def association_key(scan_key_i: str, scan_key_j: str, T_W_S_i: np.ndarray, T_W_S_j: np.ndarray,
                    max_distance_mm: float) -> str:
    """The cache key of a pair's nearest neighbours for the joint refinement (``joint.associate``): both
    prepared scans (:func:`joint_scan_key`), both start poses (W, mm) and the distance they are searched within
    (mm)."""
    h = hashlib.blake2b((scan_key_i + scan_key_j).encode(), digest_size=16)
    h.update(np.ascontiguousarray(np.stack([T_W_S_i, T_W_S_j]), np.float64).tobytes())
    h.update(np.float64(max_distance_mm).tobytes())
    return h.hexdigest()


@dataclass(frozen=True)
class ScanSummary:
    """What the correction keeps of one scan instead of its points (:func:`summarise_scan`): the ``pair_cell_mm``
    grid cells (``overlap.occupied_cells``, W) its copy thinned at the job's voxel occupies at the tracker pose,
    that placed copy's digest (:func:`cloud_digest`, the pair cache's key; empty where not asked for), the key of
    the scan prepared for the joint refinement (:func:`joint_scan_key`) and its reach (``tiles.ScanReach``: the
    tiled merge's bound of its x at the final pose)."""

    cells: np.ndarray
    digest: bytes
    joint_key: str
    reach: ScanReach


@dataclass(frozen=True)
class ReadScan:
    """A scan summarised where it was read (:func:`summarise_scan`): its :class:`ScanSummary` and, where asked for,
    the scan prepared for the joint refinement (:func:`joint_scan`; read from the scan store, kept there:
    ``joint.StoredJointScan``; else None): all the correction needs of it."""

    summary: ScanSummary
    joint: JointScan | StoredJointScan | None


def summarise_scan(points_S: np.ndarray, T_W_S: np.ndarray, voxel_mm: float, cfg: CorrectionSettings,
                   digest: bool, joint: bool, thinned_S: np.ndarray | None = None) -> ReadScan:
    """:class:`ReadScan` of a scan whose copy as the end of the job loads it (``raw_scan.read_thinned_scan``, S,
    mm) is ``points_S``, at its tracker pose ``T_W_S`` (W, mm): the grid cells and ``digest`` (if asked) of that
    copy thinned to ``voxel_mm`` (the job's, as the pairs take it; ``thinned_S`` where the caller has thinned it)
    in W, and with ``joint`` the scan at ``cfg.joint_voxel_mm``."""
    if thinned_S is None:
        thinned_S = voxel_downsample(np.asarray(points_S, float), voxel_mm)
    world = transform_points(T_W_S, thinned_S)
    summary = ScanSummary(occupied_cells(world, cfg.pair_cell_mm), cloud_digest(world) if digest else b"",
                          joint_scan_key(points_S, cfg.joint_voxel_mm), ScanReach.of(T_W_S, points_S))
    return ReadScan(summary, joint_scan(points_S, cfg.joint_voxel_mm) if joint else None)


#: the folder of the scan store that holds the scans prepared for the joint refinement while it runs
#: (:func:`summarise_stored_scan`), each file named by its contents (:func:`joint_scan_key`)
JOINT_FOLDER = "joint"
#: its folder that holds the refinement's per-pair results between its stages (its pairs' matches,
#: ``compute.StoredResults``: no worker holds them), removed when the refinement ends
KEPT_FOLDER = "kept"


def remove_joint_folder(scan_store: str | Path) -> None:
    """Remove the scan store's :data:`JOINT_FOLDER` with every scan in it: where a correction failed or was cut
    short (which scans the units that ran wrote there, only they know); the store is one job's (docs/compute.md)."""
    shutil.rmtree(Path(scan_store) / JOINT_FOLDER, ignore_errors=True)


def summarise_stored_scan(ref: ScanRef, store: StoredScans, cfg: CorrectionSettings, digest: bool, joint: bool
                          ) -> ReadScan:
    """:func:`summarise_scan` of a scan read from the scan store (a backend unit: where the scan is read); with
    ``joint`` the scan prepared for the joint refinement is written to the store (:data:`JOINT_FOLDER`) and its
    reference returned (``joint.StoredJointScan``, read by each unit that takes it: no worker holds it between
    them)."""
    read = summarise_scan(store.loaded(ref), ref.T_W_S, store.voxel_mm, cfg, digest, joint)
    if read.joint is None:
        return read
    key = read.summary.joint_key
    return ReadScan(read.summary, StoredJointScan.write(read.joint, Path(store.store) / JOINT_FOLDER / f"{key}.npz",
                                                        key))


def _summaries(job: StitchedJob, cfg: CorrectionSettings, digest: bool, backend: ComputeBackend,
               scan_store: str | None
               ) -> tuple[list[ScanSummary], list[StoredJointScan | None], list[np.ndarray | None]]:
    """:func:`summarise_scan` of every scan of ``job``: from its points where it holds them, else read from
    ``scan_store`` by a unit on ``backend``; the summaries, per scan the scan prepared for the joint refinement
    with ``cfg.joint`` where it was read on the backend, kept in the store (``joint.StoredJointScan``: on a Dask
    cluster neither this process nor a worker holds it), else None, and per scan its points thinned to the job's
    voxel (S, mm) where it holds them (thinned once: for the summary and for the pairs and the overlap RMS), else
    None."""
    scans = job.scans
    out: list[ScanSummary | None] = [None] * len(scans)
    joints: list[StoredJointScan | None] = [None] * len(scans)
    thinned: list[np.ndarray | None] = [None] * len(scans)
    held = [k for k, s in enumerate(scans) if s.points_S is not None]

    def summarise_held(k: int) -> ScanSummary:
        thinned[k] = voxel_downsample(np.asarray(scans[k].points_S, float), job.voxel_mm)
        return summarise_scan(scans[k].points_S, scans[k].T_W_S, job.voxel_mm, cfg, digest, False, thinned[k]).summary

    with pair_threads() as pair_map:
        for k, summary in zip(held, pair_map(summarise_held, held), strict=True):
            out[k] = summary
    stored = [k for k, s in enumerate(scans) if s.points_S is None]
    if stored:
        if scan_store is None:
            raise ValueError(f"correction: {len(stored)} scans without points and no scan store to read them from")
        refs = [ScanRef(k, scans[k].file, scans[k].T_W_S) for k in stored]
        fn = functools.partial(summarise_stored_scan, store=StoredScans(scan_store, job.voxel_mm), cfg=cfg,
                               digest=digest, joint=cfg.joint)
        keys = [f"summary-{_unit_digest(ref, job.voxel_mm, cfg, digest)}" for ref in refs]
        for k, read in zip(stored, backend.map(fn, refs, keys), strict=True):
            out[k], joints[k] = read.summary, read.joint
    return out, joints, thinned


def _unit_digest(ref: ScanRef, voxel_mm: float, cfg: CorrectionSettings, *flags: object) -> str:
    """A unit's name: the scan's file and pose, the voxel, the settings and ``flags``."""
    h = hashlib.blake2b(ref.file.encode(), digest_size=16)
    h.update(np.ascontiguousarray(ref.T_W_S, np.float64).tobytes())
    h.update(np.float64(voxel_mm).tobytes())
    h.update(repr((cfg, flags)).encode())
    return h.hexdigest()


def _pair_corrections(
    job: StitchedJob, summaries: Sequence[ScanSummary], local: Sequence[np.ndarray] | None, cfg: CorrectionSettings,
    network: Registrar | None, online: OnlineWork, backend: ComputeBackend, scan_store: str | None,
) -> tuple[list[tuple[int, int, PairOutcome | None]], int, list[tuple[int, int]], list[PendingPair]]:
    """The outcome of every pair of the job's scans registered at ``cfg.registered_partners``
    (``overlap.overlapping_pairs``, from each scan's grid cells in W, ``summaries``, :func:`summarise_scan`): from
    ``online.pairs`` where the job registered the pair while it measured (same clouds, covariance and settings: the
    summaries' digests), None where it is still registering there (``online.pending``: returned as
    :class:`PendingPair`), else registered here, one unit a target (``pair_stage.TargetPairs``) on ``backend``; with
    ``scan_store`` the units read their scans from it by reference
    (``pair_stage.StoredScans``: a Dask cluster's workers), else they take this process's thinned clouds ``local``
    (S, mm), of which only the scans of pairs left to register are placed in W here. Returns the outcomes in pair
    order, how many came from the cache, the pairs selected at ``cfg.max_partners_per_scan`` (the registered
    ones where the joint refinement is off), on all of which the report's overlap RMS is taken, registered or not:
    it scores the overlaps at the poses, and the pending pairs.

    Eight parameters: the job, what is known of its scans (summaries, the clouds where held), the settings and
    network, the pairs registered while measuring, and where the rest run and read their scans."""
    scans, voxel_mm = job.scans, job.voxel_mm
    stations, digests = [s.station for s in scans], [m.digest for m in summaries]
    shared = shared_cells([m.cells for m in summaries])
    selected = select_pairs(shared, stations, cfg.max_partners_per_scan)
    registering = select_pairs(shared, stations, cfg.registered_partners) if cfg.registered_partners else []
    cache, digesting = online.pairs, bool(online.pairs or online.pending)
    out: list[tuple[int, int, PairOutcome | None]] = []
    todo: dict[int, list[tuple[int, np.ndarray, int]]] = {}  # target -> (source, covariance, slot in out)
    pending: list[PendingPair] = []
    hits = 0

    def ref(k: int) -> ScanRef:
        return ScanRef(k, scans[k].file, scans[k].T_W_S)

    for i, j in registering:
        cov = pair_covariance(scans[i], scans[j], job.transfers)
        key = pair_key(digests[i], digests[j], cov, cfg.pairs) if digesting else ""
        cached = cache.get(key) if cache else None
        if cached is not None:
            hits += 1
        elif key in online.pending:
            pending.append(PendingPair(len(out), ref(i), ref(j), cov, key))
        else:
            todo.setdefault(i, []).append((j, cov, len(out)))
        out.append((i, j, cached))

    units = [TargetPairs(ref(i), tuple(ref(j) for j, _, _ in group), tuple(cov for _, cov, _ in group))
             for i, group in todo.items()]
    if scan_store is not None:
        clouds: StoredScans | HeldScans = StoredScans(scan_store, voxel_mm)
    else:  # only the scans of the pairs left are placed here
        needed = sorted({k for i, group in todo.items() for k in (i, *(j for j, _, _ in group))})
        with pair_threads() as pair_map:
            clouds = HeldScans(dict(zip(needed, pair_map(
                lambda k: transform_points(scans[k].T_W_S, local[k]), needed), strict=True)))
    registered = register_units(units, clouds, cfg.pairs, voxel_mm, backend, network)
    for group, outcomes in zip(todo.values(), registered, strict=True):
        for (_, _, slot), outcome in zip(group, outcomes, strict=True):
            out[slot] = (out[slot][0], out[slot][1], outcome)
    return out, hits, selected, pending


def _pair_figures(outcomes: Sequence[tuple[int, int, PairOutcome]], cached: int, cpu_s_a_pair: float | None
                  ) -> dict:
    """The correction section's figures of its registered pairs (``outcomes``, every one known): how many gave an
    edge, how many came from the work done while measuring (``cached``) at what CPU seconds a pair, which were
    dropped and why, and the stages the edges came from (each dropped pair logged)."""
    for i, j, o in outcomes:
        if o.dropped:
            log.warning("correction: pair (%d, %d) dropped: %s", i, j, o.dropped)
    edges = [o for _, _, o in outcomes if o.transformation is not None]
    return {
        "pairs": len(edges),
        "pairs_registered_while_measuring": cached,
        # the CPU seconds a pair took while the job measured (the registration's thread, nothing else of the worker)
        "cpu_s_a_pair_while_measuring": cpu_s_a_pair,
        "pairs_dropped": [{"i": int(i), "j": int(j), "reason": o.dropped} for i, j, o in outcomes if o.dropped],
        "stages": dict(Counter(o.stage for o in edges)),
    }


def _cpu_s_a_pair(online: OnlineWork) -> float | None:
    return round(online.pair_cpu_s / len(online.pairs), 4) if online.pairs else None


def complete_pair_checks(checks: PairChecks, cfg: CorrectionSettings, later: OnlineWork | None, scan_store: str,
                         voxel_mm: float, backend: ComputeBackend | None = None, network: Registrar | None = None
                         ) -> dict:
    """The report's pair figures (those :func:`correct_scans` leaves out of its report where ``checks`` were still
    registering: :func:`with_pair_figures` puts them in): each pending pair's outcome from ``later`` (what the job
    computed while measuring, handed over once its pairs were done: ``online_pairs.OnlinePairs.work``; None where
    that failed), else registered here as :func:`correct_scans` would, its scans read from ``scan_store``
    (``pair_stage.StoredScans``, thinned to ``voxel_mm``) on ``backend`` (this process's threads where None)."""
    out, cached = list(checks.outcomes), checks.cached
    todo: dict[int, list[PendingPair]] = {}
    for pair in checks.pending:
        outcome = later.pairs.get(pair.key) if later is not None else None
        if outcome is None:
            todo.setdefault(pair.target.index, []).append(pair)
        else:
            out[pair.slot] = (out[pair.slot][0], out[pair.slot][1], outcome)
            cached += 1
    units = [TargetPairs(group[0].target, tuple(p.source for p in group), tuple(p.covariance for p in group))
             for group in todo.values()]
    registered = register_units(units, StoredScans(scan_store, voxel_mm), cfg.pairs, voxel_mm,
                                backend or LocalBackend(), network)
    for group, outcomes in zip(todo.values(), registered, strict=True):
        for pair, outcome in zip(group, outcomes, strict=True):
            out[pair.slot] = (out[pair.slot][0], out[pair.slot][1], outcome)
    cpu_s_a_pair = checks.cpu_s_a_pair if later is None else _cpu_s_a_pair(later)
    return _pair_figures(out, cached, cpu_s_a_pair)


def with_pair_figures(report: Mapping, figures: Mapping) -> dict:
    """A correction section whose check pairs were still registering (``CorrectionResult.checks``) with their
    figures (:func:`complete_pair_checks`), in the place a complete section has them."""
    keys = list(report)
    at = keys.index("scans") + 1
    return {k: report[k] for k in keys[:at]} | dict(figures) | {k: report[k] for k in keys[at:]}


def correct_scans(
    job: StitchedJob, cfg: CorrectionSettings, network: Registrar | None = None, online: OnlineWork | None = None,
    backend: ComputeBackend | None = None, scan_store: str | None = None,
) -> CorrectionResult:
    """Correct every overlapping pair of the job's scans (:class:`StitchedJob`: thinned to its voxel first) and
    refine all poses, removing the drift of its transfers and, with its mount prior, estimating the shared
    scanner-mount correction too.

    ``network`` registers pairs where the method asks for DeepMerge (``pairs.LazyNetwork`` loads it only
    then). A pair whose registration fails its verification is dropped and logged. ``online`` holds what the job
    computed while it measured (:class:`OnlineWork`): the outcomes of pairs registered then (a pair not among them
    is registered here, so the result never depends on them), the scans prepared for the joint refinement (each
    taken out as the refinement takes it, so that none outlives the refinement: the prepared scans of a whole part
    are about half a gigabyte) and the pairs' nearest neighbours found for it at the tracker poses; the pairs it
    names as still registering (``online.pending``, only with the joint refinement, whose poses take none of them)
    are left out of the report, which then lacks its pair figures: ``CorrectionResult.checks`` holds them for
    :func:`complete_pair_checks`.
    The pairs not in the cache run on ``backend`` (``pipeline.compute``; this process's threads where None), each
    unit reading its scans from ``scan_store`` by their :attr:`StitchedScan.file` where it is given (a Dask
    cluster, docs/compute.md), the result the same to the bit either way.
    The report's ``stage_seconds`` are wall seconds of each stage. With ``[correction] joint`` (the default) the
    joint refinement gives the poses and the mount and the pose graph is not solved (it started from the tracker
    poses, not from the graph's, and the graph's figures alone were about 4 s of CPU after the last scan); without
    it the pose graph does, and the report has its costs (``graph_cost_before`` / ``_after``, ``graph_s``).
    A correction that fails or is cancelled leaves none of its scans prepared for the joint refinement in the scan
    store (:func:`remove_joint_folder`).
    """
    try:
        return _corrected(job, cfg, network, online, backend, scan_store)
    except BaseException:
        if scan_store is not None:
            remove_joint_folder(scan_store)
        raise


def _corrected(job: StitchedJob, cfg: CorrectionSettings, network: Registrar | None, online: OnlineWork | None,
               backend: ComputeBackend | None, scan_store: str | None) -> CorrectionResult:
    """:func:`correct_scans`."""
    if cfg.method in NETWORK_METHODS and network is None:
        raise ValueError(f"method {cfg.method!r} needs a DeepMerge registrar (pairs.LazyNetwork)")
    clock = _Clock()
    scans, transfers, mount_prior = job.scans, job.transfers, job.mount_prior
    online = online or OnlineWork({}, {}, {})
    backend = backend or LocalBackend()
    if online.pending and not cfg.joint:
        raise ValueError("the pose graph takes every pair: pairs still registering only with the joint refinement")
    # the joint refinement's scans read with their summaries: the backend's handles (else None)
    summaries, prepared, local = _summaries(job, cfg, bool(online.pairs or online.pending)
                                            and cfg.registered_partners > 0, backend, scan_store)
    held = all(s.points_S is not None for s in scans)
    if not held:  # the thinned clouds this process holds (the pairs' and the overlap RMS's): only where it holds all
        local = None
    clock.lap("thin_s")
    outcomes, cached, selected, pending = _pair_corrections(job, summaries, local, cfg, network, online, backend,
                                                            scan_store)
    clock.lap("pairs_s")
    edges = [(i, j, o) for i, j, o in outcomes if o is not None and o.transformation is not None]
    checks = PairChecks(tuple(outcomes), tuple(pending), cached, _cpu_s_a_pair(online)) if pending else None
    priors = [ScanPrior(s.T_W_S, s.covariance, s.station) for s in scans]
    joint, graph_figures = None, {}
    if cfg.joint:
        stored = [j for j in prepared if j is not None]
        # on a scan store the pairs' matches wait between the refinement's stages in files there, not on the workers
        state = (contextlib.nullcontext(backend) if scan_store is None
                 else StoredResults(backend, Path(scan_store) / JOINT_FOLDER / KEPT_FOLDER))
        try:
            with state as pair_backend:
                joint, associated_while_measuring = _refine_jointly(job, priors, cfg, summaries, prepared,
                                                                    online.joint_scans, online.associations,
                                                                    pair_backend)
        finally:
            _remove_stored(stored)
        clock.lap("joint_s")
        poses, mount = joint.poses, joint.mount
    else:
        graph = refine_poses(priors, [PairEdge(i, j, o.transformation, o.information, o.centre_mm)
                                      for i, j, o in edges if o.information is not None], transfers, mount_prior)
        clock.lap("graph_s")
        poses, mount = graph.poses, graph.mount
        graph_figures = {"graph_cost_before": graph.cost_before, "graph_cost_after": graph.cost_after}
    before = [s.T_W_S for s in scans]
    rms_units = _overlap_rms_units(scans, selected, before, poses)
    if held:  # on this process's clouds, else read on the backend from the store
        rms_b, rms_a = _overlap_rms(rms_units, lambda ref: local[ref.index], cfg.pairs.criteria.icp_max_distance_mm,
                                    job.voxel_mm, LocalBackend())
    else:
        rms_b, rms_a = _overlap_rms(rms_units, StoredScans(scan_store, job.voxel_mm).thinned,
                                    cfg.pairs.criteria.icp_max_distance_mm, job.voxel_mm, backend)
    clock.lap("overlap_rms_s")
    moves = [pose_error(a, b) for a, b in zip(poses, before, strict=True)]
    report = {
        "method": cfg.method,
        "scans": len(scans),
        **({} if checks is not None else _pair_figures(outcomes, cached, _cpu_s_a_pair(online))),
        "overlap_rms_mm_median_before": rms_b,
        "overlap_rms_mm_median_after": rms_a,
        "pose_change_mm_median": float(np.median([m[0] for m in moves])) if moves else 0.0,
        "pose_change_deg_median": float(np.degrees(np.median([m[1] for m in moves]))) if moves else 0.0,
        **graph_figures,
        "stage_seconds": clock.laps,
    }
    if joint is not None:
        report["joint"] = _joint_report(joint, [s.station for s in scans]) | {
            "pairs_associated_while_measuring": associated_while_measuring}
    log.info("correction: %d scans, %d pairs (%d still registering), overlap RMS %.4f -> %.4f mm", len(scans),
             len(edges), len(pending), rms_b, rms_a)
    # the joint refinement's posterior of the scans' errors; the pose graph's is not formed: the chain's prior
    covariance = joint.pose_covariance if joint is not None else chain_covariance(priors, transfers, mount_prior)
    backend.trim()   # the next stage (the tiled merge) starts from what the workers hold, not from this one's peak
    return CorrectionResult(poses, edges, report, mount, covariance, tuple(m.reach for m in summaries), checks)


def _joint_cells(unit: tuple[np.ndarray, float], scan: JointScan | StoredJointScan) -> np.ndarray:
    """The grid cells (``overlap.occupied_cells``, W) of a scan prepared for the joint refinement at its tracker pose:
    ``unit`` is that pose ``T_W_S`` and the cell (mm) (a unit of :func:`_refine_jointly`)."""
    T_W_S, cell_mm = unit
    return occupied_cells(transform_points(T_W_S, loaded_scan(scan).points_S), cell_mm)


def _remove_stored(scans: Sequence[StoredJointScan]) -> None:
    """Remove the files of the scans the joint refinement read from the scan store (:func:`summarise_stored_scan`),
    and their folder once it is empty."""
    for scan in scans:
        scan.remove()
    if scans:
        try:
            Path(scans[0].path).parent.rmdir()
        except OSError:   # another job's scans are still there, or it is gone
            pass


def _refine_jointly(job: StitchedJob, priors: list[ScanPrior], cfg: CorrectionSettings,
                    summaries: Sequence[ScanSummary], prepared: list[StoredJointScan | None],
                    cache: MutableMapping[str, JointScan], associations: Mapping[str, Association],
                    backend: ComputeBackend) -> tuple[JointResult, int]:
    """The joint refinement (``joint.refine_jointly``, its per-pair work on ``backend``) from the tracker poses (its
    correspondences are found there, not at the pose graph's, which are fitted to the same scans: ``joint`` module
    doc), on scans thinned to ``cfg.joint_voxel_mm`` (:func:`joint_scan`: ``prepared`` where read with the scans'
    ``summaries``, kept in the scan store (``joint.StoredJointScan``: each unit reads those it takes), else taken out of
    ``cache`` where prepared while the job measured, else prepared here; those this process holds are handed to the
    backend, ``ComputeBackend.put``), over every pair sharing a grid cell (``cfg.joint_max_partners_per_scan``),
    with the pairs' nearest neighbours from ``associations`` where found while the job measured. Returns it and
    the number of pairs whose neighbours came from ``associations``.

    Eight parameters: the job, its priors and settings, what is known of its scans (summaries, prepared ones,
    those prepared while measuring, their associations) and the backend."""
    scans = job.scans
    keys = [m.joint_key for m in summaries]

    def taken(k: int) -> JointScan | StoredJointScan:
        found, prepared[k] = prepared[k], None
        if found is None and cache:
            found = cache.pop(keys[k], None)
        return joint_scan(scans[k].points_S, cfg.joint_voxel_mm) if found is None else found

    with pair_threads() as pair_map:
        thinned = pair_map(taken, range(len(scans)))
    here = [k for k, t in enumerate(thinned) if isinstance(t, JointScan)]
    for k, handle in zip(here, backend.put([thinned[k] for k in here]), strict=True):
        thinned[k] = handle
    cells = backend.map(_joint_cells, [(s.T_W_S, cfg.pair_cell_mm) for s in scans],
                        [f"joint-cells-{_unit_digest(ScanRef(k, keys[k], s.T_W_S), cfg.joint_voxel_mm, cfg)}"
                         for k, s in enumerate(scans)], [(t,) for t in thinned])
    pairs = select_pairs(shared_cells(cells), [s.station for s in scans], cfg.joint_max_partners_per_scan)
    found = {}
    for i, j in pairs if associations else ():
        a = associations.get(association_key(keys[i], keys[j], scans[i].T_W_S, scans[j].T_W_S,
                                             cfg.joint_refinement.max_distance_mm))
        if a is not None:
            found[i, j] = a
    return refine_jointly(thinned, priors, pairs, [s.T_W_S for s in scans], job.transfers, job.mount_prior,
                          cfg.joint_refinement, found, backend), len(found)


def _joint_report(joint: JointResult, stations: list[int]) -> dict:
    """Figures of the joint refinement; per tracker station the mean 1-sigma (mm) of the scan origins along the
    world axes, a priori (tracker and transfers) and a posteriori (the realised counterpart of the bound); per
    pair of tracker stations the factor the posterior counts their pairs' noise information at (``joint``
    ``_dispersions``)."""
    st = np.asarray(stations)

    def per_station(cov: np.ndarray) -> dict:
        sig = np.sqrt(np.clip(np.diagonal(cov[:, :3, :3], axis1=1, axis2=2), 0.0, None))
        return {int(k): np.round(sig[st == k].mean(axis=0), 4).tolist() for k in np.unique(st)}

    return {"iterations": joint.iterations, "pairs": joint.pairs, "correspondences": joint.correspondences,
            "sigma_mm": round(joint.sigma_mm, 5), "noise_sigma_mm": round(joint.noise_sigma_mm, 5),
            "pairs_associated_anew": joint.pairs_associated_anew,
            "rms_mm_before": round(joint.rms_mm_before, 5),
            "rms_mm_after": round(joint.rms_mm_after, 5),
            "dispersion_per_station_pair": {k: round(v, 3) for k, v in joint.dispersion.items()},
            "sigma_xyz_mm_per_station": {"prior": per_station(joint.prior_covariances),
                                         "posterior": per_station(joint.covariances)}}
