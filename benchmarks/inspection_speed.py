"""Seconds of a finished job's exports and inspection (what :func:`tandemscan.daemon.jobs.outputs.write_job_outputs`
runs after ``cloud.ply``: E57 and pose log in a process of their own, alignment to CAD, deviations, report.html,
cloud_deviation.ply) on a finished job's folder, per stage, plus the inspection's numbers to compare runs. Prints
one JSON object last.

The job folder is only read: its ``cloud.ply`` (W, mm) is the final cloud, ``scans/scan-NNNN.npz`` the raw scans
(S, mm), ``report.json`` the final and tracker-stitched poses ``T_W_S`` and the anchor's ``T_F_W``; the outputs go
to ``--out`` (a temporary folder by default). The part is the configured default (``[part]``).

Usage: nice -n 10 python benchmarks/inspection_speed.py JOB_DIR [--out DIR] [--config TOML] [--json FILE]
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import os
import resource
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from clean_exit import clean_exit_on_sigterm
from results import publish
from tandemscan.config.loader import load_config
from tandemscan.daemon.jobs import outputs as job_outputs
from tandemscan.daemon.jobs.outputs import stitch_view_points
from tandemscan.pipeline.compute import LazyBackend
from tandemscan.pipeline.inspection import inspect, inspection_job, report
from tandemscan.pipeline.io.cloud_io import read_ply
from tandemscan.pipeline.io.raw_scan import read_raw_scan, thin_scan
from tandemscan.pipeline.stitching.worldmap import MapCloud

SECONDS: dict[str, float] = defaultdict(float)
TIMED = [  # (module, function, stage name): each call's seconds are added to its stage (threads may overlap)
    (inspection_job, "align", "alignment_s"),
    (inspection_job, "inspect_cloud", "inspect_cloud_s"),
    (inspect, "_best_fit_result", "best_fit_s"),
    (inspect, "find_deviation_areas", "deviation_areas_s"),
    (inspection_job, "build_report", "build_report_s"),
    (report, "overlap_quality", "overlap_quality_s"),
    (report, "_coverage_figure", "coverage_s"),
    (report, "deviation_map_png", "maps_s"),
    (inspection_job, "write_report", "write_report_s"),
    (inspection_job, "write_ply", "deviation_ply_s"),
]


def _timed(fn, name):
    @functools.wraps(fn)
    def wrapper(*a, **k):
        t0 = time.perf_counter()
        try:
            return fn(*a, **k)
        finally:
            SECONDS[name] += time.perf_counter() - t0
    return wrapper


def _cpu_s(who: int = resource.RUSAGE_SELF) -> float:
    """CPU seconds of this process, all its threads (a figure that holds on a machine shared with others), or of its
    ended child processes (``RUSAGE_CHILDREN``: the E57's)."""
    r = resource.getrusage(who)
    return r.ru_utime + r.ru_stime


def load_job(job_dir: Path, config, out_dir: Path) -> tuple[SimpleNamespace, dict, list, list | None]:
    """A stand-in for the job snapshot with what ``write_job_outputs`` reads, the job's report, the scans'
    points (S, mm) and the tracker-stitched poses (None where the job was not corrected)."""
    rep = json.loads((job_dir / "report.json").read_text(encoding="utf-8"))
    points, normals = read_ply(job_dir / "cloud.ply")
    scans, points_S = [], []
    for entry in rep["scan_log"]:
        raw = read_raw_scan(job_dir / "scans" / entry["file"])
        points_S.append(stitch_view_points(thin_scan(raw[0], rep["voxel_mm"])))  # what the end of the job passes
        scans.append(SimpleNamespace(file=job_dir / "scans" / entry["file"], tracker_station=entry["tracker_station"],
                                     reading=SimpleNamespace(timestamp_s=0.0), joints_rad=np.zeros(6),
                                     T_W_S=np.asarray(entry["T_W_S"], float), point_count=len(raw[0])))
    tracker = [np.asarray(e["T_W_S_tracker"], float) for e in rep["scan_log"]] if all(
        "T_W_S_tracker" in e for e in rep["scan_log"]) else None
    cloud = MapCloud(rep["voxel_mm"], np.asarray(points, float), np.asarray(normals, float))
    job = SimpleNamespace(job_dir=out_dir, scans=scans, worldmap=cloud, config=config, transfers=[],
                          T_F_W=np.asarray(rep["inspection"]["T_F_W_anchor"], float), pose_covariance=None,
                          plan=SimpleNamespace(name="plan", coverage_pct=rep["coverage"].get("planned_pct"),
                                               left_out=[]))
    return job, rep, points_S, tracker


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("job_dir", type=Path)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--config", default=None)
    ap.add_argument("--json", type=Path, default=None, help="also write the inspection section here")
    args = ap.parse_args()
    for module, name, stage in TIMED:
        setattr(module, name, _timed(getattr(module, name), stage))
    with contextlib.ExitStack() as stack:
        out = args.out or Path(stack.enter_context(tempfile.TemporaryDirectory()))
        out.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        job, rep, points_S, tracker = load_job(args.job_dir, load_config(args.config), out)
        t_load = time.perf_counter() - t0
        t0, c0, e0 = time.perf_counter(), _cpu_s(), _cpu_s(resource.RUSAGE_CHILDREN)
        failed: dict[str, str] = {}
        backend = stack.enter_context(LazyBackend(job.config.compute))  # the job's cloud is not tiled: makes none
        section = job_outputs.write_job_outputs(job, rep, points_S, tracker, failed=failed, backend=backend)
        total, cpu, e57_cpu = time.perf_counter() - t0, _cpu_s() - c0, _cpu_s(resource.RUSAGE_CHILDREN) - e0
        sizes = {f.name: f.stat().st_size for f in out.iterdir() if f.is_file()}
    if failed:  # no figures of outputs that were not written
        raise SystemExit(f"outputs not written: {failed}")
    if args.json:
        args.json.write_text(json.dumps(section, indent=1), encoding="utf-8")
    stats = section.get("as_measured", {}).get("stats", {})
    publish("inspection_speed", {
        "benchmark": "inspection_speed",
        "job": args.job_dir.name,
        "points": len(job.worldmap.points()),
        "scans": len(points_S),
        "load_s": round(t_load, 3),
        "exports_and_inspection_s": round(total, 3),
        "exports_and_inspection_cpu_s": round(cpu, 3),
        "e57_process_cpu_s": round(e57_cpu, 3),
        "load_avg_1min": round(os.getloadavg()[0], 2),
        "stages_s": {k: round(v, 3) for k, v in SECONDS.items()},
        "file_mb": {k: round(v / 1e6, 1) for k, v in sizes.items()},
        "verdict": section.get("verdict"),
        "areas": len(section.get("deviations", [])),
        "alignment_residual_mm": section.get("alignment", {}).get("residual_mm"),
        "rms_mm": stats.get("rms_mm"),
        "in_pct": section.get("as_measured", {}).get("tolerance", {}).get("in_pct"),
    })


if __name__ == "__main__":
    clean_exit_on_sigterm()
    main()
