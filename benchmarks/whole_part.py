"""Measure a whole part end to end on the simulated cell and print its coverage and accuracy as JSON.

Usage: ``nice .venv/bin/python benchmarks/whole_part.py [--config CELL.toml] [--part default|barrel]
[--stitch-only] [--tracker-stations N] [--time-scale S] [--resolution coarse|full] [--mounts surveyed|configured]``
(``job_mounts``: the cell's surveyed mounts unless the config names a calibration file; ``mounts`` in the JSON);
``--time-scale 1``: the simulated robots move, scan and read the tracker in real time (the vendors' speeds of the
configuration), as a real cell does, so that ``timings.after_last_scan_s`` is what an operator waits for after
the last scan (with the default 0 every motion is instant and the pairs registered while measuring lag behind
the simulator); ``--stitch-only``: the
tracker-only stitch (no correction step, no in-job inspection), which is most of the job's time;
``--tracker-stations N``: only the plan's steps while the tracker stands at its first N stations (a shorter
job for the accuracy figures: the coverage is then that of the part of the plan run); ``--resolution full``:
the scanner's full resolution (3.2 M points a scan) instead of the coarse default. ``resources`` in the JSON:
the peak resident memory (GiB) of the job's process until report.html (``peak_rss_gib_until_report``: the
product's work, before the simulator's scoring), of this process and of the largest worker process
(``getrusage``: everything, scoring included), the peak of
their sum sampled every 2 s from ``/proc``, and the disk the job folder takes (GB, its raw scans apart).
The part is planned as ``tandemscan measure --part`` does it (no plan given), the plan run on the simulated cell
(coarse resolution, the config's correction settings), and the stitched cloud scored: ``coverage_pct`` is the
share of the surface where a scanner pose fits (by mesh area, as the planner counts it) that has a cloud point
within 1 mm, ``planned_coverage_pct`` the planner's dry run; cloud to part RMS and P95 (mm), tracker-only and
after correction, scans, column moves and seconds. ``barrel`` is the 4 m fuselage barrel panel standing on the
floor (radius 2.2 m, crown 1.6 m, ``pipeline.part.barrel_panel_mesh``), written to a PLY for the job.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import resource
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import open3d as o3d
from clean_exit import clean_exit_on_sigterm
from job_mounts import add_mounts_option, chosen_mounts, job_config
from results import publish
from tandemscan.config import load_config
from tandemscan.config.inspection_template import shipped_template
from tandemscan.daemon.cell.session import CellSession
from tandemscan.daemon.jobs.runner import JobRunner
from tandemscan.daemon.plans import plan_configured_part
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.part import barrel_panel_mesh
from tandemscan.pipeline.geometry.raycast import make_scene
from tandemscan.pipeline.planning.coverage import pose_fits, triangle_geometry
from tandemscan.pipeline.planning.plan import MoveTracker, Plan, Scan
from tandemscan.sim_drivers.stitch_score import SCORE_CHUNK

_ON_SURFACE_MM = 1.0


def measured_coverage_pct(mesh: o3d.geometry.TriangleMesh, cloud_W_mm: np.ndarray, T_F_W: np.ndarray,
                          sweet_spot_mm: float, incidence_limit_rad: float) -> float:
    """Share (%) of the surface where a pose fits whose triangles hold a cloud point within 1 mm; the cloud
    (W) placed in the part frame F by ``T_F_W`` and measured a chunk at a time (a full-resolution whole
    part's 18 M points would take GBs of temporaries at once)."""
    scene = make_scene(mesh)
    area, _, _ = triangle_geometry(mesh)
    hit = np.zeros(len(area), bool)
    for lo in range(0, len(cloud_W_mm), SCORE_CHUNK):
        p = F.transform_points(T_F_W, cloud_W_mm[lo:lo + SCORE_CHUNK]).astype(np.float32)
        ans = scene.compute_closest_points(o3d.core.Tensor(p))
        near = np.linalg.norm(ans["points"].numpy() - p, axis=1) <= _ON_SURFACE_MM
        hit[ans["primitive_ids"].numpy()[near]] = True
    fits = pose_fits(mesh, sweet_spot_mm, incidence_limit_rad)
    return 100.0 * float(area[hit & fits].sum() / area[fits].sum())


def first_tracker_stations(plan: Plan, stations: int) -> Plan:
    """``plan`` up to (without) its coordinate transfer to tracker station ``stations`` (a relocation of the
    tracker before the first scan is no transfer)."""
    transfers, scanned = 0, False
    for i, step in enumerate(plan.steps):
        scanned |= isinstance(step, Scan)
        if isinstance(step, MoveTracker) and scanned:
            transfers += 1
            if transfers == stations:
                return plan.model_copy(update={"steps": plan.steps[:i]})
    return plan


def _tree_rss_bytes(root: int) -> int:
    """Resident memory (bytes) of process ``root`` and all its descendants, from ``/proc``."""
    parents: dict[int, int] = {}
    for entry in os.scandir("/proc"):
        if entry.name.isdigit():
            try:
                with open(f"/proc/{entry.name}/stat", "rb") as f:
                    parents[int(entry.name)] = int(f.read().rsplit(b")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
    tree, grew = {root}, True
    while grew:
        grown = tree | {pid for pid, parent in parents.items() if parent in tree}
        grew, tree = len(grown) > len(tree), grown
    total = 0
    for pid in tree:
        try:
            with open(f"/proc/{pid}/statm", "rb") as f:
                total += int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
        except (OSError, IndexError, ValueError):
            continue
    return total


class TreeRssSampler:
    """Peak resident memory (bytes) of this process and its workers together, sampled every ``period_s``."""

    def __init__(self, period_s: float = 2.0):
        self.peak, self._period, self._stop = 0, period_s, threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)

    def _sample(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, _tree_rss_bytes(os.getpid()))
            self._stop.wait(self._period)

    def __enter__(self) -> TreeRssSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


def disk_bytes(folder: Path) -> dict[str, int]:
    """Bytes the files under ``folder`` take on disk (allocated blocks), all and its ``scans/`` only."""
    total = scans = 0
    for path in folder.rglob("*"):
        if path.is_file():
            size = path.stat().st_blocks * 512
            total += size
            scans += size if "scans" in path.relative_to(folder).parts[:1] else 0
    return {"all": total, "scans": scans}


def resources(sampler: TreeRssSampler, disk: dict[str, int], report: dict) -> dict:
    """The ``resources`` section: peak RSS (GiB; ``ru_maxrss`` is KiB on Linux) and disk (GB);
    ``peak_rss_gib_until_report``: the job's process until report.html (``report.json`` ``resources``: before
    the simulator's scoring and this script's coverage, which run in the same process here)."""
    gib = 1 << 20
    return {
        "peak_rss_gib_until_report": report.get("resources", {}).get("peak_rss_gib"),
        "peak_rss_gib_self": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / gib, 2),
        "peak_rss_gib_largest_worker": round(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / gib, 2),
        "peak_rss_gib_all_processes_sampled": round(sampler.peak / (1 << 30), 2),
        "job_disk_gb": round(disk["all"] / 1e9, 2), "raw_scans_disk_gb": round(disk["scans"] / 1e9, 2),
    }


async def run(args: argparse.Namespace) -> dict:
    config = load_config(args.config)
    if args.transfer_samples:
        config = config.model_copy(update={"tracker": config.tracker.model_copy(
            update={"transfer_samples": args.transfer_samples})})
    config = config.model_copy(update={"scanner": config.scanner.model_copy(update={"resolution": args.resolution}),
                                       "sim": config.sim.model_copy(update={"time_scale": args.time_scale})})
    if args.stitch_only:
        config = config.model_copy(update={"correction": config.correction.model_copy(update={"enabled": False}),
                                           "inspection": config.inspection.model_copy(update={"in_job": False})})
    mounts = chosen_mounts(config, args.mounts)
    with tempfile.TemporaryDirectory() as tmp:
        if args.part == "barrel":
            mesh_file = Path(tmp) / "barrel-panel.ply"
            o3d.io.write_triangle_mesh(str(mesh_file), barrel_panel_mesh())
            config = config.model_copy(update={"part": config.part.model_copy(update={"mesh": mesh_file}),
                                               "inspection": config.inspection.model_copy(
                                                   update={"template": shipped_template("barrel-panel.toml")})})
        t = time.perf_counter()
        mesh, part_plan = plan_configured_part(config, f"whole {args.part}")
        plan_seconds = time.perf_counter() - t
        plan = part_plan.sequence.plan
        if args.tracker_stations:
            plan = first_tracker_stations(plan, args.tracker_stations)
        started = time.perf_counter()
        with TreeRssSampler() as sampler:
            async with CellSession(config) as session:
                config = job_config(config, mounts, session, Path(tmp))
                result = await JobRunner(session, plan, config, Path(tmp) / "job").run()
                T_W_F = session.cell.simulation.world.T_W_F  # scoring only: the truth of where W lies
        seconds = time.perf_counter() - started
        disk = disk_bytes(result.job_dir)
        cloud_W = np.asarray(o3d.io.read_point_cloud(str(result.cloud_file)).points)
    r, g = result.report, result.report["ground_truth"]
    before = r.get("correction", {}).get("before", g)
    limit = np.radians(config.planning.incidence_limit_deg)
    return {
        "cell": config.name, "part": args.part, "resolution": args.resolution, "mounts": mounts,
        "correction": config.correction.enabled,
        "tracker_stations_run": args.tracker_stations or part_plan.summary()["tracker_stations"],
        "coverage_pct": round(measured_coverage_pct(mesh, cloud_W, F.invert(T_W_F), config.scanner.sweet_spot_mm,
                                                      limit), 2),
        "planned_coverage_pct": round(part_plan.coverage.coverage_pct, 2),
        "scans": r["scans"], "scans_planned": r["scans_planned"], "scans_empty": len(r["scans_empty"]),
        "points_cloud": r["points_cloud"], "points_inspected": r.get("inspection", {}).get("meta", {}).get("points"),
        "characteristics": {c["id"]: [c["status"], round(c["actual_mm"], 4)]
                            for c in r.get("inspection", {}).get("characteristics", [])},
        "lift_moves": part_plan.summary()["lift_moves"], "transfers": r["transfers"],
        "unresolved_poses": r["relocalisation"]["unresolved_count"],
        "scans_untracked": r["relocalisation"]["untracked_count"],
        "robots_moved_together": len(g.get("robots_moved_together", [])),
        "tracker_only_cloud_rms_mm": before.get("cloud_rms_mm"), "cloud_rms_mm": g["cloud_rms_mm"],
        "cloud_p95_mm": g["cloud_p95_mm"], "tracker_only_pose_err_mm_median": before.get("pose_err_mm_median"),
        "pose_err_mm_median": g["pose_err_mm_median"], "timings": r["timings"],
        "plan_seconds": round(plan_seconds, 1), "job_seconds": round(seconds, 1),
        "time_scale": args.time_scale, "transfer_samples": config.tracker.transfer_samples,
        "still_noise_fraction": config.tracker.still_noise_fraction,
        "per_tracker_station": g.get("per_tracker_station"),
        "per_tracker_station_tracker_only": before.get("per_tracker_station"),
        "transfers_truth": g.get("transfers"),
        "resources": resources(sampler, disk, r), "load_average_1min": round(os.getloadavg()[0], 2),
    }


def result_name(args: argparse.Namespace) -> str:
    """The results file of this run (``results.publish``): ``whole_part`` and the variant that departs from the
    default instant, coarse, whole default part."""
    variant = [args.part] if args.part != "default" else []
    variant += ["full"] if args.resolution == "full" else []
    variant += ["realtime"] if args.time_scale == 1 else [f"timescale{args.time_scale:g}"] if args.time_scale else []
    variant += ["stitch-only"] if args.stitch_only else []
    variant += [f"stations{args.tracker_stations}"] if args.tracker_stations else []
    variant += [f"samples{args.transfer_samples}"] if args.transfer_samples else []
    return "-".join(["whole_part", *variant])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, help="cell configuration (default: the simulated cell)")
    parser.add_argument("--part", choices=["default", "barrel"], default="default")
    parser.add_argument("--stitch-only", action="store_true", help="tracker-only stitch: no correction step")
    parser.add_argument("--tracker-stations", type=int, default=0, help="run only the first N tracker stations")
    parser.add_argument("--time-scale", type=float, default=0.0,
                        help="simulated motion time x this = wall time (1: real time; default 0: instant)")
    parser.add_argument("--resolution", choices=["coarse", "full"], default="coarse",
                        help="scanner resolution (full: 3.2 M points a scan)")
    parser.add_argument("--transfer-samples", type=int, default=0,
                        help="readings averaged on each side of a transfer (default: the config's)")
    add_mounts_option(parser)
    args = parser.parse_args()
    publish(result_name(args), asyncio.run(run(args)))


if __name__ == "__main__":
    clean_exit_on_sigterm()
    main()
