"""``report.json`` of a job: what was measured and, on the simulated cell, the ground-truth scores."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from tandemscan.pipeline import frames as F
from tandemscan.pipeline.scoring import cloud_to_mesh_distances, distance_stats, pose_errors

if TYPE_CHECKING:
    from tandemscan.daemon.runner import JobRunner


def build_report(runner: JobRunner, seconds: float) -> dict:
    """The report of a finished run (mm, deg, s)."""
    report: dict = {
        "job": runner.job_dir.name,
        "plan": runner.plan.name,
        "scans": len(runner.scans),
        "transfers": len(runner.transfers),
        "points_raw": int(sum(s.point_count for s in runner.scans)),
        "points_cloud": len(runner.worldmap),
        "voxel_mm": runner.worldmap.voxel_mm,
        "installation_source": runner.config.job.installation_source,
        "seconds": round(seconds, 3),
        "transfer_log": runner.transfers,
        "correction": runner.correction,
        "scan_log": [
            {"index": s.index, "tracker_station": s.tracker_station, "points": s.point_count,
             "file": s.file.name, "T_W_S": s.T_W_S.tolist()}
            for s in runner.scans
        ],
    }
    world = runner.cell.world
    if world is not None and runner.scans:
        report["ground_truth"] = ground_truth_scores(runner)
    return report


def ground_truth_scores(runner: JobRunner) -> dict:
    """Pose errors per scan and per tracker station, and the stitched cloud's distance to the part."""
    world = runner.cell.world
    mm, deg = pose_errors([s.T_W_S for s in runner.scans], [s.T_W_S_true for s in runner.scans])
    stations = np.array([s.tracker_station for s in runner.scans])
    growth = [
        {"tracker_station": int(k), "scans": int(np.sum(stations == k)),
         "pose_err_mm_median": float(np.median(mm[stations == k])),
         "pose_err_deg_median": float(np.median(deg[stations == k]))}
        for k in np.unique(stations)
    ]
    cloud_F = F.transform_points(F.invert(world.T_W_F), runner.worldmap.points())
    d = cloud_to_mesh_distances(world.scene, cloud_F)
    cloud = distance_stats(d)
    return {
        "pose_err_mm_median": float(np.median(mm)),
        "pose_err_mm_max": float(np.max(mm)),
        "pose_err_deg_median": float(np.median(deg)),
        "pose_err_deg_max": float(np.max(deg)),
        "per_scan": [{"index": s.index, "pose_err_mm": float(a), "pose_err_deg": float(b)}
                     for s, a, b in zip(runner.scans, mm, deg, strict=True)],
        "per_tracker_station": growth,
        "cloud_rms_mm": cloud["rms_mm"],
        "cloud_p95_mm": cloud["p95_mm"],
        "cloud_max_mm": cloud["max_mm"],
        "robots_moved_together": list(world.motion.violations),
    }
