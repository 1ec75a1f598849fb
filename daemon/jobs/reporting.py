"""A job's :class:`~tandemscan.pipeline.job_report.JobReport` (``report.json``) from its end-of-job state: what was
measured, and on the simulated cell the ground-truth scores of the job's observer
(:mod:`tandemscan.daemon.cell.observer`, :func:`score_ground_truth`), taken once report.html and the exports are
written: what the operator waits for is the product's work, not the simulator's scoring."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from tandemscan.pipeline.job_report import GroundTruth, JobReport, ScanEntry, Timings, as_matrix

if TYPE_CHECKING:
    from tandemscan.daemon.jobs.snapshot import JobSnapshot


def build_job_report(job: JobSnapshot, seconds: float, tracker_poses: Sequence[np.ndarray] | None,
                     inspection: Mapping[str, Any], coverage: Mapping[str, Any], peak_rss_gib: float | None,
                     timings: Timings, ground_truth: GroundTruth | None = None,
                     failed: Mapping[str, str] | None = None) -> JobReport:
    """The report of a finished run (mm, deg, s): each scan's final pose ``T_W_S`` (W, mm) and, where the
    correction changed it, its tracker-stitched pose ``T_W_S_tracker`` (``tracker_poses``), the stages' sections,
    the observer's ``ground_truth``, the journal's resumes (``job.history``) and the outputs that could not be
    written (``failed``: name -> error).

    Nine parameters: the job's snapshot, then each stage's result the report holds, built once here."""
    tracker = [None] * len(job.scans) if tracker_poses is None else [as_matrix(T) for T in tracker_poses]
    scan_log = tuple(ScanEntry(s.index, s.tracker_station, s.point_count, s.file.name, as_matrix(s.T_W_S), T)
                     for s, T in zip(job.scans, tracker, strict=True))
    return JobReport(
        job=job.job_dir.name, plan=job.plan.name, transfers=len(job.transfers),
        points_raw=int(sum(s.point_count for s in job.scans)), points_cloud=len(job.worldmap),
        voxel_mm=job.worldmap.voxel_mm, installation_source=job.config.job.installation_source,
        seconds=round(seconds, 3), scans_planned=job.plan.scan_count,
        left_out_by_plan=tuple(a.model_dump() for a in job.plan.left_out),  # what the plan could not measure, where
        transfer_log=tuple(job.transfers), relocalisation=relocalisation_summary(job.relocalisation),
        correction=job.correction, scan_log=scan_log, inspection=inspection, coverage=coverage,
        peak_rss_gib=peak_rss_gib, timings=timings, ground_truth=ground_truth, history=job.history,
        failed_outputs=dict(failed or {}))


#: the ground-truth figures of the tracker-only stitch kept in ``correction.before``
_BEFORE_KEYS = ("pose_err_mm_median", "pose_err_mm_max", "pose_err_deg_median", "pose_err_deg_max",
                "cloud_rms_mm", "cloud_p95_mm")


def score_ground_truth(job: JobSnapshot, inspection: Mapping[str, Any],
                       tracker_stitch: JobSnapshot | None) -> GroundTruth | None:
    """On the simulated cell (``job.scorer`` set), the scorer's section of the final stitch ``job``: its
    ``ground_truth``, that of the tracker-only stitch (``tracker_stitch``: its scans at the tracker poses and the
    cloud stitched while measuring; None where the correction left the poses) and the score of the ``inspection``
    where it has an alignment. None on a real cell or for a job without scans."""
    if job.scorer is None or not job.scans:
        return None
    scores, before = job.scorer.score(job), None
    if tracker_stitch is not None and job.correction.get("enabled"):
        tracker_scores = job.scorer.score(tracker_stitch)
        before = {k: tracker_scores[k] for k in _BEFORE_KEYS}
    aligned = job.scorer.score_inspection(job, dict(inspection)) if "alignment" in inspection else None
    return GroundTruth(scores, before, aligned)


def relocalisation_summary(log: dict) -> dict:
    """The runner's relocalisation log with its figures: AGV stations located, poses scanned with a nearby view
    or not re-solved and how far off plan the AGV stood (mm, deg, maxima)."""
    located = log.get("located", [])
    out = dict(log) | {"stations_located": len(located), "unresolved_count": len(log.get("unresolved", [])),
                       "untracked_count": len(log.get("untracked", [])),
                       "adjusted_count": len(log.get("adjusted", []))}
    for key in ("off_plan_mm", "off_plan_deg"):
        values = [e[key] for e in located if key in e]
        if values:
            out[f"{key}_max"] = float(np.max(values))
    return out
