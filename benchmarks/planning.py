"""Planning benchmark: the default part and a 20 m x 3 m x 4 m train car; one JSON object on the last line.

For each part: scans, AGV stations, tracker stations (and the solver used), the exact optimum where the integer
program finishes within a generous limit, coverage by mesh area (dry run: ``coverage_pct`` of the surface where a
scanner pose fits at all, i.e. not the floor-facing underside; ``coverage_of_reachable_pct`` of what the arm can
reach; ``coverage_of_all_surface_pct`` of the whole mesh), and the planning time (s, wall and CPU of this
process including solver threads).
Run: ``nice .venv/bin/python benchmarks/planning.py``.
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np
from tandemscan.config import load_config
from tandemscan.config.models import PartConfig
from tandemscan.pipeline.part import load_part_mesh
from tandemscan.pipeline.planning.coverage import dry_run
from tandemscan.pipeline.planning.planner import plan_part
from tandemscan.pipeline.planning.tracker import solve_exact
from tandemscan.pipeline.raycast import make_scene

EXACT_LIMIT_S = 60.0
CAR = PartConfig(length_mm=20000.0, width_mm=3000.0, height_mm=4000.0, body_length_mm=18000.0)


def bench(name: str, part: PartConfig) -> dict:
    config = load_config()
    config = config.model_copy(update={"part": part})
    mesh = load_part_mesh(part)
    start = config.sim.tracking_start
    tracker_start = (start.x_mm, start.y_mm, np.radians(start.heading_deg))
    if part != load_config().part:  # the sim's start pose belongs to the default part: other parts start free
        tracker_start = None
    t, cpu = time.perf_counter(), time.process_time()
    plan = plan_part(mesh, config, tracker_start=tracker_start, name=name)
    seconds, cpu_seconds = time.perf_counter() - t, time.process_time() - cpu
    s = plan.summary()
    t = time.perf_counter()
    exact = solve_exact(plan.cover, EXACT_LIMIT_S, 10**7, plan.start_candidate)
    exact_s = time.perf_counter() - t
    coverage = dry_run(mesh, make_scene(mesh), plan.rasters, config.scanner,
                       np.radians(config.planning.incidence_limit_deg))
    return {
        "part": name,
        "coverage_pct": round(coverage.coverage_pct, 2),
        "coverage_of_reachable_pct": round(coverage.coverage_of_reachable_pct, 2),
        "coverage_of_all_surface_pct": round(coverage.coverage_of_all_pct, 2),
        "scans": s["scans"],
        "poses_without_margin": s["poses_without_margin"],
        "agv_stations": s["agv_stations"],
        "tracker_stations": s["tracker_stations"],
        "tracker_solver": s["tracker_solver"],
        "tracker_lower_bound": s["tracker_lower_bound"],
        "tracker_stations_optimal": exact.count if exact is not None else None,
        "exact_seconds": round(exact_s, 2),
        "transfers": s["transfers"],
        "plan_seconds": round(seconds, 2),
        "plan_cpu_seconds": round(cpu_seconds, 2),  # wall time on a shared machine overstates the work
    }


def main() -> int:
    default = bench("default train nose 3 m", load_config().part)
    car = bench("train car 20 m x 3 m x 4 m", CAR)
    print(json.dumps(default), file=sys.stderr)
    print(json.dumps(car), file=sys.stderr)
    out = {f"{k}": v for k, v in default.items() if k != "part"}
    out |= {f"car20m_{k}": v for k, v in car.items() if k != "part"}
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
