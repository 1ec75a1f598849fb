"""``report.json`` of a job: what was measured and, on the simulated cell, the ground-truth scores."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from tandemscan.pipeline import frames as F
from tandemscan.pipeline.scoring import cloud_to_mesh_distances, distance_stats, pose_errors

if TYPE_CHECKING:
    from tandemscan.daemon.snapshot import JobSnapshot


def build_report(job: JobSnapshot, seconds: float) -> dict:
    """The report of a finished run (mm, deg, s)."""
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
    world = job.world
    if world is not None and job.scans:
        report["ground_truth"] = ground_truth_scores(job)
    return report


def relocalisation_summary(log: dict) -> dict:
    """The runner's relocalisation log with its figures: AGV stations located, poses scanned with a nearby view
    or not re-solved, how far off plan the AGV stood and, on the simulated cell, how far the located pose is from
    the true one (mm, deg, maxima)."""
    located = log.get("located", [])
    out = dict(log) | {"stations_located": len(located), "unresolved_count": len(log.get("unresolved", [])),
                       "untracked_count": len(log.get("untracked", [])),
                       "adjusted_count": len(log.get("adjusted", []))}
    for key in ("off_plan_mm", "off_plan_deg", "err_to_truth_mm", "err_to_truth_deg"):
        values = [e[key] for e in located if key in e]
        if values:
            out[f"{key}_max"] = float(np.max(values))
    return out


def ground_truth_scores(job: JobSnapshot) -> dict:
    """Pose errors per scan and per tracker station, and the stitched cloud's distance to the part."""
    world = job.world
    mm, deg = pose_errors([s.T_W_S for s in job.scans], [s.T_W_S_true for s in job.scans])
    stations = np.array([s.tracker_station for s in job.scans])
    growth = [
        {"tracker_station": int(k), "scans": int(np.sum(stations == k)),
         "pose_err_mm_median": float(np.median(mm[stations == k])),
         "pose_err_deg_median": float(np.median(deg[stations == k]))}
        for k in np.unique(stations)
    ]
    cloud_F = F.transform_points(F.invert(world.T_W_F), job.worldmap.points())
    d = cloud_to_mesh_distances(world.scene, cloud_F)
    cloud = distance_stats(d)
    return {
        "pose_err_mm_median": float(np.median(mm)),
        "pose_err_mm_max": float(np.max(mm)),
        "pose_err_deg_median": float(np.median(deg)),
        "pose_err_deg_max": float(np.max(deg)),
        "per_scan": [{"index": s.index, "pose_err_mm": float(a), "pose_err_deg": float(b)}
                     for s, a, b in zip(job.scans, mm, deg, strict=True)],
        "per_tracker_station": growth,
        "cloud_rms_mm": cloud["rms_mm"],
        "cloud_p95_mm": cloud["p95_mm"],
        "cloud_max_mm": cloud["max_mm"],
        "robots_moved_together": list(world.robots_moved_together),
    }
