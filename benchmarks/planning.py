"""Planning benchmark: two cells x three parts; one JSON object on the last line.

Cells: the default simulated cell (Zu 7 on the AGV) and the shipped larger cell
(``config/large-cell.example.toml``: Zu 12 on a lifting column). Parts: the default 3 m train nose, the 4 m
fuselage barrel panel standing on the floor (radius 2.2 m, crown 1.6 m, ``pipeline.part.barrel_panel_mesh``) and
a 20 m x 3 m x 4 m train car. For each: scans, AGV stations, column moves, tracker stations (and the solver
used), the exact optimum where the integer program finishes within a generous limit (default cell only),
coverage by mesh area (dry run: ``coverage_pct`` of the surface where a scanner pose fits at all, i.e. not the
floor-facing underside; ``coverage_of_reachable_pct`` of what the arm can reach; ``coverage_of_all_surface_pct``
of the whole mesh), the area left out per reason (m^2), and the planning time (s, wall and CPU of this process
including solver threads; the coverage dry run included).
Run: ``nice .venv/bin/python benchmarks/planning.py``.
"""

from __future__ import annotations

import json
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
from results import publish
from tandemscan.config import load_config
from tandemscan.config.models import CellConfig, PartConfig
from tandemscan.pipeline.geometry.part import barrel_panel_mesh, load_part_mesh
from tandemscan.pipeline.planning.parameters import PartPlanning
from tandemscan.pipeline.planning.planner import plan_part
from tandemscan.pipeline.planning.tracker import solve_exact

EXACT_LIMIT_S = 60.0
CAR = PartConfig(length_mm=20000.0, width_mm=3000.0, height_mm=4000.0, body_length_mm=18000.0)
LARGE_CELL = Path(__file__).resolve().parents[1] / "config" / "large-cell.example.toml"


def bench(config: CellConfig, mesh, sim_start: bool, exact: bool) -> dict:
    """Plan ``mesh`` on ``config``; ``sim_start``: the chain starts at the sim's tracker start (it belongs to
    the default part; other parts start free)."""
    start = config.sim.tracking_start
    tracker_start = (start.x_mm, start.y_mm, np.radians(start.heading_deg)) if sim_start else None
    cell = PartPlanning.from_config(config)
    t, cpu = time.perf_counter(), time.process_time()
    plan = plan_part(mesh, cell, tracker_start=tracker_start)
    seconds, cpu_seconds = time.perf_counter() - t, time.process_time() - cpu
    s, coverage = plan.summary(), plan.coverage
    left_out = defaultdict(float)
    for lo in coverage.left_out:
        left_out[lo.reason] += lo.area_mm2 / 1e6
    out = {
        "coverage_pct": round(coverage.coverage_pct, 2),
        "coverage_of_reachable_pct": round(coverage.coverage_of_reachable_pct, 2),
        "coverage_of_all_surface_pct": round(coverage.coverage_of_all_pct, 2),
        "left_out_m2": {k: round(v, 3) for k, v in left_out.items()},
        **{k: s[k] for k in ("scans", "poses_without_margin", "poses_unseen_by_tracker", "agv_stations", "lift_moves",
                             "tracker_stations", "tracker_solver", "tracker_lower_bound", "transfers")},
        "plan_seconds": round(seconds, 2),
        "plan_cpu_seconds": round(cpu_seconds, 2),  # wall time on a shared machine overstates the work
    }
    if exact:
        t = time.perf_counter()
        optimum = solve_exact(plan.cover, EXACT_LIMIT_S, 10**7, plan.start_candidate)
        out |= {"tracker_stations_optimal": optimum.count if optimum is not None else None,
                "exact_seconds": round(time.perf_counter() - t, 2)}
    return out


def main() -> int:
    default_cell = load_config()
    cells = {"default": default_cell, "large": load_config(LARGE_CELL)}
    parts = {"nose": (load_part_mesh(default_cell.part), True), "barrel": (barrel_panel_mesh(), False),
             "car20m": (load_part_mesh(CAR), False)}
    out = {}
    for cell, config in cells.items():
        for part, (mesh, sim_start) in parts.items():
            figures = bench(config, mesh, sim_start, exact=cell == "default")
            print(json.dumps({"cell": cell, "part": part, **figures}), file=sys.stderr)
            out |= {f"{cell}_{part}_{k}": v for k, v in figures.items()}
    publish("planning", out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
