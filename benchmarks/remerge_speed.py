"""Seconds of the end of a job's re-merge (``daemon.jobs.finish.merge_stage``: every scan file merged into a 1 mm
voxel map at its final pose) on a finished job's folder, against one map taking every scan in turn (what the
re-merge did before it merged consecutive scans in groups of their own on two threads and combined them once,
``worldmap.VoxelMap.combined``). Prints one JSON object last.

The job folder is only read: ``report.json`` (each scan's file and final ``T_W_S``, W, mm) and
``scans/scan-NNNN.npz`` (S, mm). The two ways run in turn ``--repeat`` times (the median is printed, and every
run: this machine's memory is much slower the first time a process touches it, so single runs scatter), each
with wall and CPU seconds; both must give the same voxels and counts, and means within rounding (the largest
difference is printed).

Usage: nice -n 10 python benchmarks/remerge_speed.py JOB_DIR [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from results import publish
from tandemscan.daemon.jobs.finish import MERGE_GROUPS, merge_stage
from tandemscan.pipeline.io.raw_scan import read_raw_scan
from tandemscan.pipeline.stitching.worldmap import VoxelMap


def _cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def one_map(job: SimpleNamespace, poses: list[np.ndarray], voxel_mm: float) -> VoxelMap:
    """Every scan merged into one map in turn, read from its file (the re-merge before the groups)."""
    worldmap = VoxelMap(voxel_mm)
    for T, s in zip(poses, job.scans, strict=True):
        worldmap.add_scan(T, *read_raw_scan(s.file, np.float32))
    return worldmap


def timed(fn, *args) -> tuple[VoxelMap, float, float]:
    """``fn(*args)`` read once (its batch merged), with its wall and CPU seconds."""
    t, c = time.perf_counter(), _cpu_s()
    worldmap = fn(*args)
    len(worldmap)
    return worldmap, time.perf_counter() - t, _cpu_s() - c


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("job_dir", type=Path)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--voxel-mm", type=float, default=1.0)
    args = ap.parse_args()
    rep = json.loads((args.job_dir / "report.json").read_text(encoding="utf-8"))
    job = SimpleNamespace(scans=[SimpleNamespace(file=args.job_dir / "scans" / e["file"]) for e in rep["scan_log"]])
    poses = [np.asarray(e["T_W_S"], float) for e in rep["scan_log"]]
    runs: dict[str, list[tuple[float, float]]] = {"grouped": [], "one_map": []}
    largest_mm = 0.0
    for _ in range(args.repeat):
        grouped, *g = timed(merge_stage, args.voxel_mm, job, poses)
        runs["grouped"].append(tuple(g))
        single, *o = timed(one_map, job, poses, args.voxel_mm)
        runs["one_map"].append(tuple(o))
        if len(grouped) != len(single) or not np.array_equal(grouped.counts(), single.counts()):
            raise SystemExit("the grouped re-merge gave other voxels than one map")
        largest_mm = max(largest_mm, float(np.abs(grouped.points() - single.points()).max()))
        voxels = len(grouped)
        del grouped, single

    def summary(name: str) -> dict:
        wall, cpu = np.array(runs[name]).T
        return {"wall_s_median": round(float(np.median(wall)), 3), "cpu_s_median": round(float(np.median(cpu)), 3),
                "wall_s": [round(float(w), 3) for w in wall], "cpu_s": [round(float(c), 3) for c in cpu]}

    publish("remerge_speed", {
                      "benchmark": "remerge_speed", "job": args.job_dir.name, "scans": len(poses), "voxels": voxels,
                      "groups": MERGE_GROUPS, "cores": os.cpu_count(), "grouped": summary("grouped"),
                      "one_map": summary("one_map"), "largest_point_difference_mm": largest_mm,
                      "load_avg_1min": round(os.getloadavg()[0], 2)})


if __name__ == "__main__":
    main()
