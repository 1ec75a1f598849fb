"""What a finished job leaves for the quality engineer besides ``cloud.ply``: ``cloud.e57`` (one scan per
pose with its world pose, plus the merged cloud) and ``poses.csv`` in the job's world frame W, and, where W
is registered to the CAD frame F, ``report.html`` with ``figures/`` and ``cloud_deviation.ply`` in frame F.

The registration is the job's own, the same on a real and a simulated cell: from where the runner placed W in
the plan's frame F (the part frame, relocalisation's anchor, Eq. 5) the cloud is aligned to the CAD by
``[inspection] alignment`` (best fit, RPS on reference spheres, or none:
:mod:`tandemscan.pipeline.inspection.alignment`); a job that did not place W (relocalisation off, the target
never seen) skips the inspection with the reason recorded. The CAD is the configured part mesh (``[part]``),
never the mesh a simulator scans. On the simulated cell the job's scorer then scores the alignment and the
deviation areas against the world's truth (``ground_truth.inspection``, docs/inspection.md), once every
output is written (``job_report.score_ground_truth``).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import multiprocessing
import time
from collections.abc import Mapping, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import open3d as o3d
from tandemscan.config.inspection_template import InspectionTemplate, find_template, load_template
from tandemscan.config.loader import ConfigError
from tandemscan.config.models import CellConfig
from tandemscan.daemon.calibration.verify import verdict_context
from tandemscan.daemon.store.part_results import HISTORY_FILE
from tandemscan.drivers.shared_array import share
from tandemscan.drivers.worker import init_worker
from tandemscan.pipeline.compute import LazyBackend
from tandemscan.pipeline.geometry.part import load_part_mesh
from tandemscan.pipeline.inspection.inspect import CadSurface, InspectionError
from tandemscan.pipeline.inspection.inspection_job import (
    AlignmentStart,
    InspectionOutputs,
    InspectionSettings,
    Measurement,
    PlacedScans,
    ReportOutput,
    align_and_inspect,
)
from tandemscan.pipeline.inspection.point_uncertainty import JobUncertainty, ScanCover
from tandemscan.pipeline.inspection.report import InspectedPart, ReportFacts, StitchViews
from tandemscan.pipeline.inspection.tile_inspection import TiledInspection
from tandemscan.pipeline.io.export import (
    ArrayBlocks,
    PointBlocks,
    PosedScan,
    ScanExports,
    write_ply,
    write_scan_exports,
)
from tandemscan.pipeline.io.raw_scan import read_thinned_scan
from tandemscan.pipeline.planning.coverage import CoverageFigures
from tandemscan.pipeline.stitching.tiles import TiledCloud, TilePoints
from tandemscan.pipeline.stitching.worldmap import MapCloud

if TYPE_CHECKING:
    from tandemscan.daemon.jobs.snapshot import JobSnapshot

log = logging.getLogger(__name__)

STITCH_VIEW_POINTS = 20_000  # per scan, for the overlap figure
EXPORT_FILES = {"e57": "cloud.e57", "pose_log": "poses.csv"}


def _posed_scans(job: JobSnapshot, points_S: Sequence[np.ndarray] | None = None) -> list[PosedScan]:
    """The job's scans at their poses with their thinned points (S, mm; ``points_S`` where the caller has
    them, else read, thinned at ``[job] voxel_mm`` and to :func:`stitch_view_points` here, one file at a
    time) and their full point counts."""
    scans = []
    for k, s in enumerate(job.scans):
        points = (stitch_view_points(read_thinned_scan(s.file, job.config.job.voxel_mm)) if points_S is None
                  else points_S[k])
        meta = {"tracker_station": s.tracker_station, "timestamp_s": s.reading.timestamp_s,
                **{f"joint{i + 1}_deg": float(np.degrees(q)) for i, q in enumerate(s.joints_rad)}}
        scans.append(PosedScan(s.file.stem, s.T_W_S, points, meta, s.point_count))
    return scans


def _thin(points: np.ndarray) -> np.ndarray:
    return points[:: max(1, len(points) // STITCH_VIEW_POINTS)]


def stitch_view_points(points_S: np.ndarray) -> np.ndarray:
    """The points of a scan (S, mm) the inspection's stitch view takes (every k-th, under twice
    ``STITCH_VIEW_POINTS``; thinning them again leaves them as they are): all the end of a job still needs of
    a scan once its correction is done. A float32 copy (12 B a point, held from the map's hand-over to the
    inspection: at 714 scans 0.18 GB, not 0.36), so that the scan's array can be freed; its readers place it in
    float64 (``frames.transform_points``)."""
    return _thin(points_S).astype(np.float32)


def _accuracy(report: Mapping) -> dict:
    """report.html's accuracy table: the job's scan and coordinate transfer counts (``report``'s ``scans`` and
    ``transfers``)."""
    return {"scans": report.get("scans"), "coordinate transfers": report.get("transfers")}


@dataclass(frozen=True)
class JobExports:
    """What :func:`export_job` wrote for a finished job: its report's ``inspection`` and ``coverage`` sections,
    the process's peak memory until then (GiB, :func:`peak_rss_gib`), the seconds of its stages
    (``cloud_ply_s``: the time to hand ``cloud.ply`` to its thread, ``exports_and_inspection_s`` includes waiting
    for it) and the outputs that could not be written, each with its error (``failed``: ``cloud_ply``, ``e57``
    with the pose log, ``inspection``; the others are written all the same)."""

    inspection: dict
    coverage: dict
    peak_rss_gib: float | None
    stages_s: dict[str, float]
    failed: dict[str, str]


def export_job(job: JobSnapshot, points_S: Sequence[np.ndarray] | None = None,
               tracker_poses: Sequence[np.ndarray] | None = None, *, backend: LazyBackend) -> JobExports:
    """Write ``cloud.ply`` (W, mm) and the inspection exports of a finished job into its folder; runs where
    ``job.worldmap`` (the final cloud) lives. ``points_S``: the scans' points (S, mm) thinned at ``[job] voxel_mm``
    or to :func:`stitch_view_points` (else read and thinned here; the E57 reads the full scans from their files);
    ``tracker_poses``: the tracker-stitched poses ``T_W_S`` (W, mm) where the correction changed them (None: not
    corrected); ``backend``: the end of the job's compute backend (a tiled cloud's inspection). ``cloud.ply``, the
    E57 with the pose log and the inspection run side by side; one that fails does not stop the others and is named
    in :attr:`JobExports.failed`."""
    t = [time.perf_counter()]
    failed: dict[str, str] = {}
    with ThreadPoolExecutor(1, thread_name_prefix="cloud-ply") as pool:  # written while the inspection computes
        cloud_ply = pool.submit(_write_cloud_ply, job.job_dir / "cloud.ply", job.worldmap)
        t.append(time.perf_counter())
        figures = {"scans": len(job.scans), "transfers": len(job.transfers)}
        # report.html, the E57 and the pose log
        inspection = write_job_outputs(job, figures, points_S, tracker_poses, failed=failed, backend=backend)
        coverage = inspection.get("coverage") or plan_coverage(job).as_dict()
        _wait(cloud_ply, "cloud_ply", failed)  # complete before the job is reported done
        t.append(time.perf_counter())
    stages = dict(zip(("cloud_ply_s", "exports_and_inspection_s"), np.round(np.diff(t), 3).tolist(), strict=True))
    return JobExports(inspection, coverage, peak_rss_gib(), stages, failed)


def _wait(future: Future, name: str, failed: dict[str, str]) -> None:
    """Wait for the output ``name`` written by ``future``; its error, if any, goes into ``failed`` (logged)."""
    try:
        future.result()
    except Exception as e:  # noqa: BLE001 - named in the report, which fails the job once written
        log.error("%s not written: %s: %s", name, type(e).__name__, e, exc_info=e)
        failed[name] = f"{type(e).__name__}: {e}"


def _write_cloud_ply(path: Path, cloud: MapCloud | TiledCloud) -> Path:
    """``cloud.ply`` (W, mm: points and unit normals) of the job's cloud, streamed a tile at a time where it was
    merged by tiles."""
    return cloud.write_ply(path) if isinstance(cloud, TiledCloud) else write_ply(path, cloud.points(), cloud.normals())


def _point_blocks(cloud: MapCloud | TiledCloud) -> PointBlocks:
    """The job's cloud's points as the E57 writer takes them in another process, a block or a tile at a time: its
    tiles' files, or its points copied into shared memory (``shared_array.share``: pickled by name)."""
    return cloud if isinstance(cloud, TiledCloud) else ArrayBlocks(share(cloud.points()))


def _every_kth(cloud: MapCloud | TiledCloud, step: int) -> TilePoints:
    """The job's cloud's every ``step``-th voxel (points, normals, counts: the inspected cloud, ``[inspection]
    max_points``), read a tile at a time where it was merged by tiles."""
    if isinstance(cloud, TiledCloud):
        return cloud.every_kth(step)
    counts = cloud.counts()
    return TilePoints(cloud.points()[::step], cloud.normals()[::step], None if counts is None else counts[::step])


def peak_rss_gib() -> float | None:
    """Peak resident memory (GiB) of this process so far (``VmHWM``, Linux ``/proc/self/status``; None where
    there is none): read when report.html is written, it is what the process that finished the job (the
    daemon's map worker, one per job, or ``tandemscan measure``) needed for it."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            kib = next(int(line.split()[1]) for line in f if line.startswith("VmHWM:"))
    except (OSError, StopIteration, ValueError, IndexError):
        return None
    return round(kib / (1 << 20), 3)


def write_job_outputs(job: JobSnapshot, report: Mapping, points_S: Sequence[np.ndarray] | None = None,
                      tracker_poses: Sequence[np.ndarray] | None = None, *, failed: dict[str, str],
                      backend: LazyBackend) -> dict:
    """Write the E57, the pose log and (when registered to CAD) the inspection report of a finished job
    (``report``: the job's ``scans`` and ``transfers`` counts for report.html's accuracy table; ``points_S``: the
    scans thinned at ``[job] voxel_mm`` or to :func:`stitch_view_points`, and ``tracker_poses``: the
    tracker-stitched poses where the correction changed them, None where not corrected; ``backend``: the end of the
    job's compute backend, made here only to inspect a tiled cloud).

    Returns the inspection section for the job's ``report.json``: the same numbers as report.html. The E57
    (the full scans streamed from their files) and the pose log are written in a process of their own
    (``export.write_scan_exports``, spawned, ``[daemon] worker_niceness`` below this one: pye57 holds the GIL
    while it packs the points) while the inspection computes on the thinned scans. Where one of them fails the
    other is written all the same and its error goes into ``failed`` (``e57``, ``inspection``).
    """
    scans = _posed_scans(job, points_S)
    to_export = _scan_exports(job, scans)  # holds the cloud's shared copy until the process is done
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"), initializer=init_worker,
                             initargs=(job.config.daemon.worker_niceness,)) as pool:
        exports = pool.submit(write_scan_exports, to_export)
        try:
            section = _inspection_section(job, report, scans, tracker_poses, backend)
        except Exception as e:  # noqa: BLE001 - named in the report, which fails the job once written
            log.error("inspection failed: %s: %s", type(e).__name__, e, exc_info=e)
            failed["inspection"] = f"{type(e).__name__}: {e}"
            section = {"failed": failed["inspection"], "files": dict(EXPORT_FILES)}
        _wait(exports, "e57", failed)
    return section


def _scan_exports(job: JobSnapshot, scans: list[PosedScan]) -> ScanExports:
    """What ``poses.csv`` and ``cloud.e57`` are written from in their own process (``export.write_scan_exports``):
    ``scans`` without their thinned points, the scans' raw files, and the job's cloud (``job.worldmap``: its
    points in shared memory, or its tiles' files), frame W, mm."""
    return ScanExports(job.job_dir / EXPORT_FILES["pose_log"], job.job_dir / EXPORT_FILES["e57"],
                       tuple(dataclasses.replace(s, points_S_mm=_NO_POINTS, point_count=s.size) for s in scans),
                       tuple(Path(r.file) for r in job.scans),
                       _point_blocks(job.worldmap) if len(job.worldmap) else None)


_NO_POINTS = np.empty((0, 3))


def _inspection_section(job: JobSnapshot, report: Mapping, scans: list[PosedScan],
                        tracker_poses: Sequence[np.ndarray] | None, backend: LazyBackend) -> dict:
    """The inspection written into the job folder and its report.json section (or why there is none)."""
    files = dict(EXPORT_FILES)
    reason = (
        "inspection.in_job is off" if not job.config.inspection.in_job
        else "no registration of the world frame to the CAD frame" if job.T_F_W is None
        else "empty cloud" if len(job.worldmap) == 0
        else ""
    )
    if reason:
        log.warning("inspection skipped: %s", reason)
        return {"skipped": reason, "files": files}
    T_F_W = np.asarray(job.T_F_W, float)
    points = len(job.worldmap)
    tiled = isinstance(job.worldmap, TiledCloud)  # its figures from every point, tile by tile (TiledInspection)
    limit, setting = sample_bound(job.config, tiled)
    step = -(-points // limit)  # ceil: every step-th voxel (map key order)
    if step > 1:
        log.info("inspecting every %d-th of the cloud's %d points (%s)", step, points, setting)
    sample = _every_kth(job.worldmap, step)
    try:
        out = _inspect(job, report, scans, sample, T_F_W, tracker_poses, points, _whole_cloud(job, backend))
    except (InspectionError, ConfigError) as e:  # the measurement stands; the report says why it has none
        log.warning("inspection failed: %s", e)
        return {"failed": str(e), "files": files}
    files |= {"html": out.html.name} | ({"deviation_ply": out.ply.name} if out.ply is not None else {})
    files |= {"qif": out.qif.name} if out.qif else {}
    return out.data | {"T_F_W": out.data["alignment"]["T_F_W"], "T_F_W_anchor": T_F_W.tolist(), "files": files}


def _whole_cloud(job: JobSnapshot, backend: LazyBackend) -> TiledInspection | None:
    """Where the job's cloud is tiled (``tiles.TiledCloud``): its inspection tile by tile on the end of the job's
    compute ``backend`` (``tile_inspection.TiledInspection``); else None."""
    cloud = job.worldmap
    return TiledInspection(cloud.tiles, cloud.store, backend.get()) if isinstance(cloud, TiledCloud) else None


def _inspect(job: JobSnapshot, report: Mapping, scans: list[PosedScan], sample: TilePoints, T_F_W: np.ndarray,
             tracker_poses: Sequence[np.ndarray] | None, cloud_points: int, whole: TiledInspection | None
             ) -> InspectionOutputs:
    """The inspection of the job's cloud (``sample``: of its ``cloud_points`` points those inspected, W, mm, each
    the mean of its ``counts`` scan points), aligned to the CAD from the anchor's ``T_F_W``, written into the job
    folder with each point's uncertainty (:func:`job_uncertainty`); the stitch view shows the tracker-only stitch
    (Eq. 1) and, where corrected, the final one. ``whole``: the tiled cloud ``sample`` is an even sample of, whose
    deviation figures, areas and PLY come from every point (``inspection_job.run_inspection``).

    Eight parameters: the job and its report so far, the scans at their final poses and, where the correction
    changed them, their tracker-stitched poses; the cloud as inspected beside its full size and, where tiled, the
    whole of it; and the anchor's ``T_F_W`` the alignment starts from."""
    cloud_W, counts = sample.points_mm, sample.counts
    job_dir = job.job_dir
    tracker_only = [s.T_W_S for s in scans] if tracker_poses is None else list(tracker_poses)
    view_S = [_thin(s.points_S_mm) for s in scans]
    before = PlacedScans(view_S, tracker_only)
    after = None if tracker_poses is None else PlacedScans(view_S, [s.T_W_S for s in scans])
    template_file = find_template(job.config.part.mesh, configured=job.config.inspection.template)
    template = None if template_file is None else load_template(template_file)
    mesh = load_part_mesh(job.config.part)
    part = InspectedPart(CadSurface(mesh), template, part_labels(job.config, template, template_file),
                         _history(job_dir))
    settings = InspectionSettings.from_section(job.config.part_inspection(), template)
    measured = Measurement(cloud_W, sample.normals, job_uncertainty(job, scans, counts), StitchViews(before, after))
    facts = ReportFacts(
        title=f"Inspection report, {job_dir.name}",
        meta={"job": job_dir.name, "plan": job.plan.name, "cell": job.config.name,
              "alignment to CAD": job.config.inspection.alignment,
              "points": points_inspected(len(cloud_W), cloud_points, whole is not None, job.config)},
        accuracy=_accuracy(report),
        coverage=plan_coverage(job, mesh),
    )
    start = AlignmentStart(T_F_W, "W placed in F by the anchor reading (Eq. 5)", T_F_W,
                           np.array([s.T_W_S[:3, 3] for s in scans]))
    return align_and_inspect(measured, part, settings, ReportOutput(job_dir, facts, json_name=None), start,
                             verdict_context(job.config), whole)


def sample_bound(config: CellConfig, tiled: bool) -> tuple[int, str]:
    """The most points of the job's cloud its inspection takes here (every k-th voxel beyond) and the setting that
    bounds them: ``[inspection] max_points`` or, for a tiled cloud, the smaller of it and
    ``[compute] report_points``."""
    if tiled and config.compute.report_points < config.inspection.max_points:
        return config.compute.report_points, "[compute] report_points"
    return config.inspection.max_points, "[inspection] max_points"


def points_inspected(sample: int, cloud: int, tiled: bool, config: CellConfig) -> str:
    """report.html's "points": those inspected of the cloud's and the setting that bounds them
    (:func:`sample_bound`)."""
    if sample == cloud:
        return str(cloud)
    setting = sample_bound(config, tiled)[1]
    if not tiled:
        return f"{sample} of the cloud's {cloud} ({setting})"
    return (f"{sample} of the cloud's {cloud} for the best fit, U and the maps ({setting}); every point for the "
            "deviation areas, the verdict on them, the deviation figures, cloud_deviation.ply and, in their "
            "regions, a template's datum frame, characteristics and close-ups")


def plan_coverage(job: JobSnapshot, mesh: o3d.geometry.TriangleMesh | None = None) -> CoverageFigures:
    """What the job's plan covers and leaves out (report.json ``coverage``), with where a scanner pose fits on the
    part's CAD ``mesh`` for the measured share (none: that share stays unknown)."""
    if mesh is None:
        return CoverageFigures(job.plan.coverage_pct, tuple(job.plan.left_out))
    return CoverageFigures.of_plan(job.plan, mesh, job.config.scanner.sweet_spot_mm,
                                   math.radians(job.config.planning.incidence_limit_deg))


def _history(job_dir: Path) -> dict:
    """The part's earlier results the daemon put in the job's folder (``part_results.HISTORY_FILE``), by
    characteristic; none for a job run without the daemon."""
    path = job_dir / HISTORY_FILE
    return json.loads(path.read_text())["characteristics"] if path.is_file() else {}


def part_labels(config: CellConfig, template: InspectionTemplate | None, template_file: Path | None
                ) -> dict[str, str]:
    """The measured part as the report and results.qif name it: part number (``[job] part_number``, else the
    template's), serial and the template file."""
    number = config.job.part_number or (template.part_number if template is not None else None)
    named = {"part_number": number, "serial": config.job.serial, "measuring_system": config.name,
             "template": None if template_file is None else str(template_file)}
    return {k: v for k, v in named.items() if v is not None}


def job_uncertainty(job: JobSnapshot, scans: Sequence[PosedScan], counts: np.ndarray | None) -> JobUncertainty | None:
    """The uncertainty model of the job's cloud (``point_uncertainty.JobUncertainty``): its poses' errors jointly
    (the mount's at the installation's prior: the calibration's covariance, or the nominal mounts' build
    tolerance; ``PoseCovariance.with_installation_at_prior``), the scans' thinned points placed in W for which
    scans each point came from (their KD tree built from now on, beside the alignment: ``ScanCover.prepared``),
    the voxels' point counts and the scanner's noise; None where the end of the job left no pose covariance."""
    if job.pose_covariance is None:
        return None
    cover = ScanCover([s.points_S_mm for s in scans], [s.T_W_S for s in scans],
                      np.array([len(s.points_S_mm) if s.point_count is None else s.point_count for s in scans], float),
                      np.array([np.asarray(s.T_W_S)[:3, 3] for s in scans]), np.arange(len(scans)))
    return JobUncertainty(job.pose_covariance.with_installation_at_prior(), cover.prepared(),
                          job.config.scanner.noise_sigma_mm, counts)
