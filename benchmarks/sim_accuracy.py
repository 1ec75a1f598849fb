"""Run the default job on the simulated cell and print its accuracy figures (mm, deg, s) as JSON.

Usage: python benchmarks/sim_accuracy.py [--resolution coarse|full] [--plan FILE|generated] [--config FILE]
[--mounts surveyed|configured] (``job_mounts``: the job stitches with the cell's surveyed mounts unless the config
names a calibration file; ``mounts`` in the JSON).
``--plan generated`` plans the whole configured part first (``tandemscan plan``; ``plan_seconds``).
The last line of output is one JSON object with keys scans (measured), scans_planned, scans_empty (no point in
the depth window), relocalisation figures (AGV stations located, poses scanned with a nearby view, unresolved
poses, located-vs-true AGV pose, largest drift off plan), transfers, pose_err_mm_median, pose_err_mm_max,
pose_err_deg_median, cloud_rms_mm, cloud_p95_mm for the tracker-only stitch, ``corrected_*`` after DeepMerge
correction, pose-graph and joint refinement (when ``[correction] enabled``; ``joint_sigma_xyz_mm_per_station``:
the joint refinement's prior and posterior 1-sigma per tracker station), ``after_last_scan_s`` (last step committed
-> report.html) and ``correction_cpu_s`` (report.json ``timings``), and seconds (the job; ``job_cpu_seconds`` of
this process).
"""

from __future__ import annotations

import argparse
import asyncio
import tempfile
import time
from pathlib import Path

from clean_exit import clean_exit_on_sigterm
from generated_plan import generated_plan
from job_mounts import add_mounts_option, chosen_mounts, job_config
from results import publish
from tandemscan.config import load_config
from tandemscan.daemon.cell.session import CellSession
from tandemscan.daemon.jobs.runner import JobRunner
from tandemscan.daemon.plans import default_plan_path
from tandemscan.pipeline.planning.plan import Plan


def _rounded(value: float | None, digits: int) -> float | None:
    return None if value is None else round(value, digits)


async def run(args: argparse.Namespace) -> dict:
    config = load_config(args.config)
    config = config.model_copy(update={"scanner": config.scanner.model_copy(update={"resolution": args.resolution})})
    plan_seconds = None
    if args.plan == "generated":
        t = time.perf_counter()
        plan = generated_plan(config)
        plan_seconds = round(time.perf_counter() - t, 2)
    else:
        plan = Plan.load(Path(args.plan) if args.plan else default_plan_path())
    mounts = chosen_mounts(config, args.mounts)
    async with CellSession(config) as session:
        started, cpu = time.perf_counter(), time.process_time()
        with tempfile.TemporaryDirectory() as tmp:
            config = job_config(config, mounts, session, Path(tmp))
            result = await JobRunner(session, plan, config, Path(tmp) / "job").run()
    r, g = result.report, result.report["ground_truth"]
    correction = r.get("correction", {})
    tracker_only = correction.get("before", g)  # without correction the final figures are tracker-only
    reloc = r["relocalisation"]
    figures = {
        "resolution": args.resolution,
        "mounts": mounts,
        "plan": plan.name,
        "scans_planned": r["scans_planned"],
        "scans": r["scans"],
        "scans_empty": len(r["scans_empty"]),
        "relocalise": reloc["enabled"],
        "agv_stations_located": reloc["stations_located"],
        "poses_adjusted": reloc["adjusted_count"],
        "poses_unresolved": reloc["unresolved_count"],
        "agv_off_plan_mm_max": _rounded(reloc.get("off_plan_mm_max"), 1),
        "agv_located_err_mm_max": _rounded(g["relocalisation"].get("err_to_truth_mm_max"), 4),
        "transfers": r["transfers"],
        "points_raw": r["points_raw"],
        "pose_err_mm_median": round(tracker_only["pose_err_mm_median"], 4),
        "pose_err_mm_max": round(tracker_only["pose_err_mm_max"], 4),
        "pose_err_deg_median": round(tracker_only["pose_err_deg_median"], 5),
        "cloud_rms_mm": round(tracker_only["cloud_rms_mm"], 4),
        "cloud_p95_mm": round(tracker_only["cloud_p95_mm"], 4),
    }
    if correction.get("enabled"):
        figures |= {
            "corrected_pose_err_mm_median": round(g["pose_err_mm_median"], 4),
            "corrected_pose_err_mm_max": round(g["pose_err_mm_max"], 4),
            "corrected_pose_err_deg_median": round(g["pose_err_deg_median"], 5),
            "corrected_cloud_rms_mm": round(g["cloud_rms_mm"], 4),
            "corrected_cloud_p95_mm": round(g["cloud_p95_mm"], 4),
            "correction_seconds": round(correction.get("seconds", float("nan")), 2),
        }
        joint = correction.get("joint")
        if joint is not None:
            figures["joint_sigma_xyz_mm_per_station"] = joint["sigma_xyz_mm_per_station"]
    figures |= {"after_last_scan_s": r["timings"]["after_last_scan_s"],
                "correction_cpu_s": r["timings"]["correction_cpu_s"],
                "stages_s": r["timings"].get("stages_s")}
    figures |= {"seconds": round(time.perf_counter() - started, 2),
                "job_cpu_seconds": round(time.process_time() - cpu, 2)}
    return figures if plan_seconds is None else figures | {"plan_seconds": plan_seconds}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", choices=["coarse", "full"], default="coarse")
    parser.add_argument("--plan", help="plan file, or 'generated' to plan the whole part (default: the band plan)")
    parser.add_argument("--config", type=Path)
    add_mounts_option(parser)
    args = parser.parse_args()
    plan = ("-" + (args.plan if args.plan == "generated" else Path(args.plan).stem)) if args.plan else ""
    publish("sim_accuracy" + plan + ("-full" if args.resolution == "full" else ""), asyncio.run(run(args)))


if __name__ == "__main__":
    clean_exit_on_sigterm()
    main()
