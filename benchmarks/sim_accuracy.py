"""Run the default job on the simulated cell and print its accuracy figures (mm, deg, s) as JSON.

Usage: python benchmarks/sim_accuracy.py [--resolution coarse|full] [--plan FILE] [--config FILE]
The last line of output is one JSON object with keys scans, transfers, pose_err_mm_median, pose_err_mm_max,
pose_err_deg_median, cloud_rms_mm, cloud_p95_mm, seconds (after correct + refine when ``[deepmerge] enabled``),
and ``correction``: the method, pairs, seconds and the tracker-only figures (``before``).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import tempfile
import time
from pathlib import Path

from tandemscan.config import load_config
from tandemscan.daemon.cli import default_plan_path
from tandemscan.daemon.runner import JobRunner
from tandemscan.pipeline.plan import Plan
from tandemscan.sim_drivers.cell import build_cell


async def run(args: argparse.Namespace) -> dict:
    config = load_config(args.config)
    config = config.model_copy(update={"scanner": config.scanner.model_copy(update={"resolution": args.resolution})})
    plan = Plan.load(args.plan or default_plan_path())
    cell = build_cell(config)
    await cell.connect()
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        result = await JobRunner(cell, plan, config, Path(tmp) / "job").run()
    await cell.close()
    r, g = result.report, result.report["ground_truth"]
    return {
        "resolution": args.resolution,
        "scans": r["scans"],
        "transfers": r["transfers"],
        "points_raw": r["points_raw"],
        "pose_err_mm_median": round(g["pose_err_mm_median"], 4),
        "pose_err_mm_max": round(g["pose_err_mm_max"], 4),
        "pose_err_deg_median": round(g["pose_err_deg_median"], 5),
        "cloud_rms_mm": round(g["cloud_rms_mm"], 4),
        "cloud_p95_mm": round(g["cloud_p95_mm"], 4),
        "seconds": round(time.perf_counter() - started, 2),
        "correction": {k: r["correction"][k] for k in ("enabled", "method", "pairs", "seconds", "before")
                       if k in r["correction"]},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", choices=["coarse", "full"], default="coarse")
    parser.add_argument("--plan", type=Path)
    parser.add_argument("--config", type=Path)
    print(json.dumps(asyncio.run(run(parser.parse_args()))))


if __name__ == "__main__":
    main()
