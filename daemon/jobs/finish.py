"""The end of a job in one pass (docs/end-of-job.md), where the job's world map lives.

After the last scan's commit: every scan's copy thinned at the job's ``[job] voxel_mm``, made as the scan was merged
(:func:`load_scans`; a full-resolution scan is 3.2 M points, 369 of them would not fit in memory), the stitch
corrected on those copies (:func:`correct_stage`: the pairs registered while the job measured are reused, the joint
refinement solved, or the pose graph where it is off), the cloud merged once at the final poses from the scan
files, one at a time on each core (:func:`merge_stage`; the map built while measuring is kept when nothing was
corrected), then ``cloud.ply``, the E57 (full scans streamed from their files), the pose log and the inspection
written, ``report.json`` is built once (``pipeline.job_report.JobReport``) and written once (``write_job_report``),
then the simulator's observer scores the job (``reporting.score_ground_truth``, none on a real cell) into its own
file beside it (``write_ground_truth``). Each
stage returns a frozen result; the tracker-stitched poses and the refined ones stay separate, and whether the poses
were corrected is known from the correction stage. Frames: poses ``T_W_S`` in the job's world frame W, points in the
scanner frame S, mm.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from tandemscan.daemon.jobs.outputs import JobExports, export_job, stitch_view_points
from tandemscan.daemon.jobs.reporting import build_job_report, score_ground_truth
from tandemscan.pipeline.compute import LazyBackend, trim_heap
from tandemscan.pipeline.io.raw_scan import read_raw_scan, read_thinned_scan
from tandemscan.pipeline.job_report import JobReport, Timings, write_ground_truth, write_job_report
from tandemscan.pipeline.registration.parallel import pair_threads
from tandemscan.pipeline.stitching.tiles import ScanReach, TiledCloud, TileScan, merge_tiles, scan_x_extent
from tandemscan.pipeline.stitching.worldmap import MapCloud, VoxelMap

if TYPE_CHECKING:
    from tandemscan.daemon.jobs.records import ScanRecord
    from tandemscan.daemon.jobs.snapshot import JobSnapshot
    from tandemscan.pipeline.registration.correction import OnlineWork, PairChecks
    from tandemscan.pipeline.registration.pose_covariance import PoseCovariance

log = logging.getLogger(__name__)

#: the end of a job merges its scans in this many groups of consecutive scans, each into a map of its own
#: (:func:`merge_stage`)
MERGE_GROUPS = 8


@dataclass(frozen=True)
class LoadedScans:
    """Every scan's points in its scanner frame S thinned to one centroid per occupied voxel of edge
    ``voxel_mm`` (float64, mm; ``registration.sampling.voxel_downsample``), or the scan itself where that would
    not halve it (float32, a coarse scan: ``raw_scan.read_thinned_scan``), in the order of ``job.scans``; where
    the end reads the scans from the store (``ComputeConfig.reads_scan_store``) only what it takes of them there: their
    stitch-view points (``outputs.stitch_view_points``) and ``reaches``, each scan's ``tiles.ScanReach`` at its
    tracker pose."""

    voxel_mm: float
    points_S: tuple[np.ndarray, ...]
    reaches: tuple[ScanReach, ...] = ()


@dataclass(frozen=True)
class CorrectionOutcome:
    """The correction stage: the report's ``correction`` section and the final poses ``T_W_S`` (W, mm; refined
    where ``corrected``, else the tracker-stitched ones of Eq. 1), one per scan of ``job.scans``; ``checks``: its
    check pairs still registering (``correction.PairChecks``, the section without pair figures until
    :func:`report_job` completes them)."""

    section: dict
    poses: tuple[np.ndarray, ...]
    corrected: bool
    pose_covariance: PoseCovariance | None = None  # their errors jointly, scans numbered as in ``job.scans``
    checks: PairChecks | None = None
    reaches: tuple[ScanReach, ...] = ()  # each scan's bound of x at any pose (``tiles.ScanReach``)


class OutputsNotWritten(OSError):
    """An output of a finished job (``cloud.ply``, the E57 and pose log, the inspection) could not be written; the
    job's ``report.json`` names it (``failed_outputs``)."""


@dataclass(frozen=True)
class FinishedJob:
    """What the end of a job produced: its report (``report.json`` with, on the simulated cell, the observer's
    scores, written beside it as ``ground_truth.json``) and the correction stage."""

    report: JobReport
    correction: CorrectionOutcome


def load_scans(job: JobSnapshot) -> LoadedScans:
    """Every scan of ``job.scans`` as its copy thinned at ``[job] voxel_mm``: the copy the map's owner kept as it
    merged the scan (``job.scan_copies``, ``stitcher.merge_scan``: taken from there, not read), else its file read
    once (one a core at a time). The correction thins to that voxel first, and thinning a thinned copy again
    changes nothing (its pairs and pose graph are those of the full scans; only its joint refinement, thinning the
    copy to its coarser ``joint_voxel_mm``, weighs each finer voxel once). A coarse scan, not halved by the
    thinning, is kept whole, so the correction at coarse resolution is that of the scans as stored. Where the
    end reads the scans from the store (``ComputeConfig.reads_scan_store``), their stitch-view points and reaches only
    (what the map's owner kept there, ``stitcher.merge_scan``)."""
    voxel_mm = job.config.job.voxel_mm
    at_voxel = job.worldmap is not None and job.worldmap.voxel_mm == voxel_mm
    kept = job.scan_copies if job.scan_copies is not None and at_voxel else {}

    def copy_of(scan: ScanRecord) -> np.ndarray:
        copy = kept.pop(str(scan.file), None)
        return read_thinned_scan(scan.file, voxel_mm) if copy is None else copy

    def view_of(scan: ScanRecord) -> tuple[np.ndarray, ScanReach]:
        view = kept.pop(str(scan.file), None)
        if view is None:
            copy = read_thinned_scan(scan.file, voxel_mm)
            view = stitch_view_points(copy), ScanReach.of(scan.T_W_S, copy)
        return view

    with pair_threads() as thread_map:  # one file a core at a time
        if job.config.compute.reads_scan_store:
            views, reaches = zip(*thread_map(view_of, job.scans), strict=True) if job.scans else ((), ())
            loaded = LoadedScans(voxel_mm, tuple(views), tuple(reaches))
        else:
            loaded = LoadedScans(voxel_mm, tuple(thread_map(copy_of, job.scans)))
    kept.clear()  # the end of the job holds them now
    return loaded


def correct_stage(job: JobSnapshot, loaded: LoadedScans | None, online: OnlineWork | None, backend: LazyBackend
                  ) -> CorrectionOutcome:
    """The correction (``pose_correction.correct_job``) of the scans that saw something, when ``[correction]`` is
    enabled and there are two of them; otherwise the tracker stitch stands, with the tracker chain's covariance.
    ``loaded`` None: this process holds no scan's points, the backend's workers read and summarise them from the
    scan store (``correction.summarise_scan``), and the outcome has each scan's ``tiles.ScanReach``. ``backend``: the
    end of the job's, made here where it corrects."""
    from tandemscan.daemon.jobs.pose_correction import correct_job, tracker_chain_covariance  # the registration stack

    tracker = tuple(np.asarray(s.T_W_S, float) for s in job.scans)
    measured = [k for k, s in enumerate(job.scans) if s.point_count > 0]  # a scan that saw nothing: nothing to do
    view = dataclasses.replace(job, scans=[job.scans[k] for k in measured])
    if not corrects(job):
        chain = tracker_chain_covariance(view) if measured else None
        return CorrectionOutcome({"enabled": False}, tracker, False, _numbered(chain, measured))
    points = [None if loaded is None else loaded.points_S[k] for k in measured]
    section, refined, covariance, checks, measured_reaches = correct_job(view, points, online, backend.get())
    poses, reaches = list(tracker), [ScanReach.of(T, np.zeros((0, 3))) for T in tracker]  # none: saw nothing
    for k, T, reach in zip(measured, refined, measured_reaches, strict=True):
        poses[k], reaches[k] = T, reach
    return CorrectionOutcome(section, tuple(poses), True, _numbered(covariance, measured), checks, tuple(reaches))


def corrects(job: JobSnapshot) -> bool:
    """Whether :func:`correct_stage` corrects the poses of ``job`` (``CorrectionOutcome.corrected``): ``[correction]``
    enabled and two scans that saw something."""
    return job.config.correction.enabled and sum(s.point_count > 0 for s in job.scans) > 1


def _numbered(covariance: PoseCovariance | None, measured: Sequence[int]) -> PoseCovariance | None:
    """``covariance`` of the scans ``measured`` (indices into the job's scans) with its scans numbered so."""
    if covariance is None:
        return None
    return dataclasses.replace(covariance, scan_ids=np.asarray(measured, np.int64)[covariance.scan_ids])


def merge_stage(voxel_mm: float, scan_files: Sequence[Path], poses: Sequence[np.ndarray]) -> VoxelMap:
    """A job's cloud: every raw scan file of ``scan_files`` merged into a voxel map (edge ``voxel_mm``, mm) at its
    pose ``T_W_S`` of ``poses`` (Eq. 1), read (points and normals, float32 as stored) one at a time on each thread.
    Consecutive scans (neighbours on the part) are merged in :data:`MERGE_GROUPS` maps of their own, one thread per
    core, and the maps combined once (``VoxelMap.combined``): the same cloud to the rounding of its sums."""
    groups = [g for g in np.array_split(np.arange(len(scan_files)), MERGE_GROUPS) if len(g)]

    def merged(group: np.ndarray) -> VoxelMap:
        worldmap = VoxelMap(voxel_mm)
        for k in group:
            worldmap.add_scan(poses[k], *read_raw_scan(scan_files[k], np.float32))
        return worldmap

    if not groups:
        return VoxelMap(voxel_mm)
    with pair_threads() as thread_map:
        return VoxelMap.combined(thread_map(merged, groups))


def scan_x_bounds(job: JobSnapshot, voxel_mm: float, poses: Sequence[np.ndarray], points_S: Sequence[np.ndarray]
                  ) -> tuple[tuple[float, float], ...]:
    """Each scan's bound of its points' x in W (mm; ``tiles.scan_x_extent`` at its final pose of ``poses``, from
    its copy thinned at ``[job] voxel_mm``, ``points_S``; ``voxel_mm`` the merge's): all the tiled merge needs of the
    copies, so that they can be freed before it."""
    return tuple(scan_x_extent(T, p, job.config.job.voxel_mm, voxel_mm) for T, p in zip(poses, points_S, strict=True))


def _tiled_merge_x_bounds(job: JobSnapshot, outcome: CorrectionOutcome, loaded: LoadedScans | None,
                          voxel_mm: float) -> tuple[tuple[float, float], ...]:
    """The bounds of x (W, mm) :func:`merged_cloud` takes, in voxels of edge ``voxel_mm`` (the merge's), where the
    correction changed the poses and ``[compute] tile_mm`` merges by tiles (else none): from the thinned copies where
    this process holds them (:func:`scan_x_bounds`), else from each scan's ``tiles.ScanReach`` the correction
    returned."""
    if not (outcome.corrected and job.config.compute.tile_mm):
        return ()
    if loaded is not None:
        return scan_x_bounds(job, voxel_mm, outcome.poses, loaded.points_S)
    return reach_x_bounds(job, outcome.reaches, outcome.poses, voxel_mm)


def reach_x_bounds(job: JobSnapshot, reaches: Sequence[ScanReach], poses: Sequence[np.ndarray], voxel_mm: float
                   ) -> tuple[tuple[float, float], ...]:
    """Each scan's bound of x (W, mm) at its pose of ``poses`` from its ``tiles.ScanReach`` of ``reaches``, in
    voxels of edge ``voxel_mm`` (the merge's): :func:`scan_x_bounds` without the copies."""
    return tuple(r.x_bound(T, job.config.job.voxel_mm, voxel_mm) for r, T in zip(reaches, poses, strict=True))


def tracker_map(job: JobSnapshot, measured: VoxelMap, reaches: Sequence[ScanReach]) -> VoxelMap:
    """The map of ``job``'s scans at their tracker poses (``job.scans``' ``T_W_S``): ``measured``, the one merged
    while the job measured, or where its owner merged none and kept each scan's reach instead (``reaches``: the
    scan-store path, ``stitcher.merge_scan``) merged now from the scan files (:func:`merge_stage`)."""
    if not reaches:
        return measured
    return merge_stage(measured.voxel_mm, [s.file for s in job.scans], [s.T_W_S for s in job.scans])


def merged_cloud(job: JobSnapshot, voxel_mm: float, poses: Sequence[np.ndarray],
                 x_bounds_mm: Sequence[tuple[float, float]], backend: LazyBackend) -> MapCloud | TiledCloud:
    """The job's cloud at its final ``poses`` (W, mm) in voxels of edge ``voxel_mm``: with ``[compute] tile_mm``
    merged by slabs of W on the end of the job's compute ``backend`` (``tiles.merge_tiles``, docs/compute.md
    "Tiles": each unit reads only the scans whose bound of x, ``x_bounds_mm`` (:func:`scan_x_bounds`), meets its
    slab, from the scan store) and left in the tiles' files (``tiles.TiledCloud``: the exports read it a tile at a
    time); else here (:func:`merge_stage`)."""
    from tandemscan.daemon.jobs.pose_correction import in_job  # the registration stack, as correct_stage

    compute = job.config.compute
    if not compute.tile_mm:
        return merge_stage(voxel_mm, [s.file for s in job.scans], poses).frozen()
    store = compute.store_of(job.job_dir)
    refs = [TileScan(in_job(Path(s.file), job.job_dir), T, *bound)
            for s, T, bound in zip(job.scans, poses, x_bounds_mm, strict=True)]
    return TiledCloud(voxel_mm, str(store), merge_tiles(refs, voxel_mm, compute.tile_mm, store, backend.get()))


@dataclass(frozen=True)
class JobOutputs:
    """The end of a job up to its report (:func:`finish_outputs`): the job at its final poses with its cloud
    (``final``: ``worldmap`` the finished cloud, ``correction`` the section so far), the correction stage (whose
    check pairs may still be registering: ``CorrectionOutcome.checks``), the exports and inspection, the
    tracker-stitched poses ``T_W_S`` (W, mm) where corrected and, for the simulator's observer, the tracker stitch;
    ``seconds`` the job until its exports, ``stages_s`` the seconds of each stage so far; ``backend`` the stages' one
    compute backend, still open for the report's check pairs (closed by :func:`report_job` or :func:`drop_outputs`).
    Kept where the map lives until :func:`report_job`."""

    final: JobSnapshot
    correction: CorrectionOutcome
    exports: JobExports
    tracker_poses: list[np.ndarray] | None
    tracker_stitch: JobSnapshot | None
    seconds: float
    stages_s: Mapping[str, float]
    backend: LazyBackend


def finish_job(job: JobSnapshot, started: float, measured_at: float,
               online: OnlineWork | None = None, stages: Mapping[str, float] | None = None,
               loaded: LoadedScans | None = None) -> FinishedJob:
    """Correct, merge, export, inspect and report a measured job in one pass (:func:`finish_outputs`, then
    :func:`report_job`): ``online`` names no pair still registering (``OnlineWork.pending``), or those pairs are
    registered before the report."""
    return report_job(finish_outputs(job, started, measured_at, online, stages, loaded), measured_at, None)


def finish_outputs(job: JobSnapshot, started: float, measured_at: float,
                   online: OnlineWork | None = None, stages: Mapping[str, float] | None = None,
                   loaded: LoadedScans | None = None) -> JobOutputs:
    """Correct, merge, export and inspect a measured job: all of its end but the report (:func:`report_job`), which
    alone waits for the check pairs still registering where ``online`` names some (``OnlineWork.pending``: with the
    joint refinement no pose takes them). It takes over ``job.worldmap``, the map stitched while the job measured
    (tracker poses), and leaves there the finished job's cloud (``worldmap.MapCloud``; with ``[compute]
    tile_mm`` a ``tiles.TiledCloud``, whose tiles' files are removed once the exports and the score have read
    them), so that the caller, holding no other reference, lets the end of the job free the map's sums. Memory: the
    thinned scans until the correction is done, the maps of one merge and one cloud at a time and one full scan a
    core; where the correction changes the poses, the map stitched while measuring (its sums: 64 B a voxel of the
    whole part) is dropped before the correction and the cloud merged anew at the corrected poses (on the simulated
    cell its cloud is kept, float32, for the score of the tracker stitch, ``correction.before``). On the scan-store
    path (``ComputeConfig.reads_scan_store``) no map was merged while measuring (``stitcher.merge_scan``): the cloud at
    the tracker poses is merged from the files where it is needed (:func:`tracker_map`; uncorrected, by
    :func:`merged_cloud`). Each raw scan file is read at most twice here: by the merge at the corrected poses and by
    the E57 (on the simulated cell on that path a third time, for the tracker stitch's score).
    ``started`` and ``measured_at`` are ``time.monotonic()`` at the job's start and at its last step's commit;
    ``online``: what the job computed while it measured (``registration.correction.OnlineWork``: registered pairs, scans
    prepared for the joint refinement); ``stages`` (s) are timings of the work before this call; ``loaded``: the
    scans as :func:`load_scans` reads them, where they were read ahead (else they are read here). The stages share
    one compute backend (``compute.LazyBackend``: one ``LocalCluster`` or scheduler client for the whole end of the
    job, started by the first stage that needs it), closed here where this fails or is cancelled, else handed on
    with the outputs."""
    backend = LazyBackend(job.config.compute)
    try:
        return _outputs_on(backend, job, started, online, dict(stages or {}), loaded)
    except BaseException:  # failed or cancelled: no cluster or client left behind
        backend.close()
        raise


def _outputs_on(backend: LazyBackend, job: JobSnapshot, started: float, online: OnlineWork | None,
                timings: dict[str, float], loaded: LoadedScans | None) -> JobOutputs:
    """:func:`finish_outputs` on the end of the job's ``backend``; ``timings`` (s) gets its stages'."""
    if loaded is None:
        t = time.perf_counter()
        loaded = load_scans(job)
        timings["read_s"] = round(time.perf_counter() - t, 3)
    reaches = loaded.reaches  # where the map's process merged no scan: the scan-store path (load_scans)
    if job.config.compute.reads_scan_store:  # the workers read the scans from the store (docs/compute.md)
        view_S, loaded = loaded.points_S, None  # only their stitch-view points were loaded (load_scans)
    else:
        view_S = tuple(stitch_view_points(p) for p in loaded.points_S)  # all the exports need of the copies
    measured, job.worldmap = job.worldmap, None
    voxel_mm, tracker_stitch = measured.voxel_mm, None
    if corrects(job):  # the cloud is merged anew at the corrected poses: the map's sums freed before the correction
        if job.scorer is not None:  # the observer scores the tracker stitch too: its cloud (float32)
            tracker_stitch = dataclasses.replace(job, worldmap=tracker_map(job, measured, reaches).frozen(np.float32))
        measured = None
    trim_heap()  # what the copies and the map freed back to the system: the correction starts from what is held
    outcome = correct_stage(job, loaded, online, backend)
    x_bounds = _tiled_merge_x_bounds(job, outcome, loaded, voxel_mm)  # all the tiled merge needs of the copies
    del loaded  # the copies freed before the merge
    trim_heap()
    t = time.perf_counter()
    tracker_poses = None
    if outcome.corrected:
        tracker_poses = [s.T_W_S for s in job.scans]
        job.worldmap = merged_cloud(job, voxel_mm, outcome.poses, x_bounds, backend)
    elif reaches:  # the tracker stitch merged from the scan files on the backend, as the corrected one
        bounds = reach_x_bounds(job, reaches, outcome.poses, voxel_mm)
        job.worldmap = merged_cloud(job, voxel_mm, outcome.poses, bounds, backend)
    else:
        job.worldmap = measured.frozen()
    del measured
    timings["merge_s"] = round(time.perf_counter() - t, 3)
    final = dataclasses.replace(
        job, scans=[dataclasses.replace(s, T_W_S=T) for s, T in zip(job.scans, outcome.poses, strict=True)],
        correction=outcome.section, pose_covariance=outcome.pose_covariance)
    seconds = time.monotonic() - started  # the job until its exports
    try:
        exports = export_job(final, view_S, tracker_poses, backend=backend)
    except BaseException:
        _remove_tiles(final)
        raise
    return JobOutputs(final, outcome, exports, tracker_poses, tracker_stitch, seconds,
                      {**timings, **outcome.section.get("stage_seconds", {}), **exports.stages_s}, backend)


def report_job(outputs: JobOutputs, measured_at: float, later: OnlineWork | None,
               stages: Mapping[str, float] | None = None) -> FinishedJob:
    """The report of a job whose outputs are written (:func:`finish_outputs`): the correction's check pairs
    completed where they were still registering (``pose_correction.complete_checks``, from ``later``, what the pair
    worker handed over once they were done; a failure there is named in the correction section,
    ``pair_checks_failed``, the poses and outputs stand), ``report.json`` built and written once, then the
    simulator's observer's scores beside it. ``stages`` (s): timings of the work beside the outputs. An export that
    failed (``JobExports.failed``) is named in the report, which is written all the same, and then fails the job
    (:class:`OutputsNotWritten`). The tiles' files of a tiled cloud are removed once the exports and the score
    have read them, and the outputs' compute backend closed (``JobOutputs.backend``: done, failed or cancelled)."""
    from tandemscan.daemon.jobs.pose_correction import complete_checks  # the registration stack, as correct_stage
    from tandemscan.pipeline.registration.correction import with_pair_figures

    final, outcome, exports = outputs.final, outputs.correction, outputs.exports
    timings = {**outputs.stages_s, **(stages or {})}
    try:
        if outcome.checks is not None:
            t = time.perf_counter()
            try:
                figures = complete_checks(final, outcome.checks, later, outputs.backend.get())
            except Exception as e:  # noqa: BLE001 - checks of the stitch: the poses and outputs stand without them
                log.warning("check pairs not registered: %s", e)
                figures = {"pair_checks_failed": f"{type(e).__name__}: {e}"}
            timings["pair_checks_s"] = round(time.perf_counter() - t, 3)
            outcome = dataclasses.replace(outcome, section=with_pair_figures(outcome.section, figures), checks=None)
            final = dataclasses.replace(final, correction=outcome.section)
        timings_s = Timings(round(time.monotonic() - measured_at, 3), outcome.section.get("cpu_seconds"), timings)
        report = build_job_report(final, outputs.seconds, outputs.tracker_poses, exports.inspection, exports.coverage,
                                  exports.peak_rss_gib, timings_s, failed=exports.failed)
        report_file = write_job_report(report, final.job_dir)
        if exports.failed:
            raise OutputsNotWritten("; ".join(f"{k} not written: {v}" for k, v in exports.failed.items())
                                    + f" (named in {report_file})")
        t = time.perf_counter()  # the simulator's observer, after the report: beside it, in its own file
        ground_truth = score_ground_truth(final, exports.inspection, outputs.tracker_stitch)
        if ground_truth is not None:
            ground_truth = dataclasses.replace(
                ground_truth, scores={**ground_truth.scores, "scoring_s": round(time.perf_counter() - t, 3)})
            write_ground_truth(ground_truth, final.job_dir)
            report = dataclasses.replace(report, ground_truth=ground_truth)
    finally:
        with outputs.backend:  # closed, also where removing the tiles fails
            _remove_tiles(final)
    return FinishedJob(report, outcome)


def left_on_disk(outputs: JobOutputs) -> TiledCloud | None:
    """The files ``outputs`` leave until their report (:func:`report_job` removes them): a tiled cloud's tiles
    (``tiles.TiledCloud``: its ``remove()`` deletes them from any process that reaches the scan store), else None."""
    cloud = outputs.final.worldmap
    return cloud if isinstance(cloud, TiledCloud) else None


def drop_outputs(outputs: JobOutputs) -> None:
    """Let go of the outputs of a job that ended before its report: its tiles' files removed (a tiled cloud) and
    its compute backend closed."""
    with outputs.backend:
        _remove_tiles(outputs.final)


def _remove_tiles(final: JobSnapshot) -> None:
    if isinstance(final.worldmap, TiledCloud):
        final.worldmap.remove()  # the tiles' files, once cloud.ply and the E57 hold the cloud
