"""``tandemscan plan [--part MESH] [--out plan.toml] [--png plan.png]``: plan a whole part (docs/planning.md).

Writes the plan (the runner's format), ``<out>-report.json`` (counts, tracker solver and bound, coverage and
the areas left out) and, with ``--png``, the top view. Bad input ends with one error line and status 2.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from rich.console import Console


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``plan`` sub-command to the main CLI's sub-parsers."""
    p = subparsers.add_parser("plan", help="plan AGV stations, scans and tracker transfers for a part")
    p.add_argument("--config", type=Path, help="cell configuration TOML (default: the simulated cell)")
    p.add_argument("--part", type=Path, help="part mesh STL/PLY/OBJ in mm (default: the parametric train nose)")
    p.add_argument("--out", type=Path, help="plan file .toml/.json (default: <job.out_dir>/plan.toml)")
    p.add_argument("--png", type=Path, help="also draw the plan's top view to this PNG")
    p.set_defaults(func=cmd_plan)
    return p


def cmd_plan(args: argparse.Namespace) -> int:
    """Plan the configured part; the tracker chain starts where the tracking robot stands (``sim.tracking_start``)."""
    from tandemscan.daemon.cli import UsageError, _load_config_with_overrides
    from tandemscan.pipeline.part import PartMeshError, load_part_mesh
    from tandemscan.pipeline.planning.coverage import dry_run
    from tandemscan.pipeline.planning.planner import plan_part
    from tandemscan.pipeline.planning.sequence import SequenceError
    from tandemscan.pipeline.planning.stations import StationPlanningError
    from tandemscan.pipeline.planning.tracker import TrackerPlanningError
    from tandemscan.pipeline.raycast import make_scene

    config = _load_config_with_overrides(args)
    out = Path(args.out) if args.out else config.job.out_dir / "plan.toml"
    part_name = str(config.part.mesh) if config.part.mesh else "parametric train nose"
    start = config.sim.tracking_start
    try:
        mesh = load_part_mesh(config.part)
        plan = plan_part(mesh, config, tracker_start=(start.x_mm, start.y_mm, np.radians(start.heading_deg)),
                         name=out.stem, part=part_name)
    except (PartMeshError, StationPlanningError, TrackerPlanningError, SequenceError) as e:
        raise UsageError(str(e)) from e
    coverage = dry_run(mesh, make_scene(mesh), plan.rasters, config.scanner,
                       np.radians(config.planning.incidence_limit_deg))
    out.parent.mkdir(parents=True, exist_ok=True)
    plan.sequence.plan.save(out)
    report_file = out.with_name(out.stem + "-report.json")
    report = {"plan": str(out), "part": part_name, **plan.summary(), "coverage": coverage.as_dict(),
              "tracker_stations_xy_heading": [[round(x, 1), round(y, 1), round(float(np.degrees(h)), 2)]
                                              for x, y, h in plan.tracker_poses]}
    report_file.write_text(json.dumps(report, indent=1), encoding="utf-8")
    if args.png:
        from tandemscan.daemon.plan_figure import draw_plan

        args.png.parent.mkdir(parents=True, exist_ok=True)
        draw_plan(plan, config.installation.T_T_S.matrix(), Path(args.png))
    s = plan.summary()
    Console().print(
        f"[bold]plan[/bold] {out}: {s['scans']} scans at {s['agv_stations']} AGV stations, {s['tracker_stations']} "
        f"tracker stations ({s['tracker_solver']}, lower bound {s['tracker_lower_bound']}), {s['transfers']} "
        f"transfers; coverage {coverage.coverage_pct:.1f} % of the surface a pose fits "
        f"({coverage.coverage_of_reachable_pct:.1f} % of what the arm reaches); planned in {s['plan_seconds']:.1f} s; "
        f"report {report_file}")
    return 0
