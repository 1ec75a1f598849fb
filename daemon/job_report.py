"""``report.json`` of a job: what was measured and, on the simulated cell, the ground-truth scores that the
job's observer writes (:mod:`tandemscan.daemon.observer`), added once report.html and the exports are written
(:func:`add_ground_truth`): what the operator waits for is the product's work, not the simulator's scoring."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from tandemscan.daemon.snapshot import JobSnapshot


def build_job_report(job: JobSnapshot, seconds: float, tracker_poses: Sequence[np.ndarray] | None = None) -> dict:
    """The report of a finished run (mm, deg, s); each scan's final pose ``T_W_S`` (W, mm) and, where the
    correction changed it, its tracker-stitched pose ``T_W_S_tracker`` (``tracker_poses``)."""
    report: dict = {
        "job": job.job_dir.name,
        "plan": job.plan.name,
        "scans": len(job.scans),
        "transfers": len(job.transfers),
        "points_raw": int(sum(s.point_count for s in job.scans)),
        "points_cloud": len(job.worldmap),
        "voxel_mm": job.worldmap.voxel_mm,
        "installation_source": job.config.job.installation_source,
        "seconds": round(seconds, 3),
        "scans_planned": job.plan.scan_count,
        "left_out_by_plan": [a.model_dump() for a in job.plan.left_out],  # what the plan could not measure, where
        "scans_empty": [s.index for s in job.scans if s.point_count == 0],
        "transfer_log": job.transfers,
        "relocalisation": relocalisation_summary(job.relocalisation),
        "correction": job.correction,
        "scan_log": [
            {"index": s.index, "tracker_station": s.tracker_station, "points": s.point_count,
             "file": s.file.name, "T_W_S": s.T_W_S.tolist()}
            for s in job.scans
        ],
    }
    if tracker_poses is not None:
        for entry, T in zip(report["scan_log"], tracker_poses, strict=True):
            entry["T_W_S_tracker"] = np.asarray(T).tolist()
    return report


#: the ground-truth figures of the tracker-only stitch kept in ``correction.before``
_BEFORE_KEYS = ("pose_err_mm_median", "pose_err_mm_max", "pose_err_deg_median", "pose_err_deg_max",
                "cloud_rms_mm", "cloud_p95_mm")


def add_ground_truth(report: dict, job: JobSnapshot, tracker_stitch: Callable[[], JobSnapshot] | None = None
                     ) -> None:
    """On the simulated cell (``job.scorer`` set), add to ``report`` the scorer's ``ground_truth`` of the final
    stitch ``job``, that of the tracker-only stitch (``tracker_stitch()``: its scans at the tracker poses and
    their cloud, built when called; where the correction changed the poses) as ``correction.before``, and the score
    of the inspection (``ground_truth.inspection``, where the report has an alignment). A real cell's report
    is left as it is."""
    if job.scorer is None or not job.scans:
        return
    report["ground_truth"] = job.scorer.score(job)
    if tracker_stitch is not None and report.get("correction", {}).get("enabled"):
        before = job.scorer.score(tracker_stitch())
        report["correction"] = {**report["correction"], "before": {k: before[k] for k in _BEFORE_KEYS}}
    if "alignment" in report.get("inspection", {}):
        report["ground_truth"]["inspection"] = job.scorer.score_inspection(job, report["inspection"])


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
