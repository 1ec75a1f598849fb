"""``tandemscan plan [--part MESH] [--out plan.toml] [--png plan.png]``: plan a whole part (docs/planning.md).

Writes the plan (the runner's format, stating the part it was made for and the areas it leaves out),
``<out>-report.json`` (counts, tracker solver and bound, coverage and the areas left out) and, with ``--png``,
the top view. ``measure --part MESH`` without ``--plan`` plans the part the same way. Bad input ends with one
error line and status 2.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from rich.console import Console
from tandemscan.daemon.cli.command import UsageError, config_from_args
from tandemscan.daemon.plans import PlanPartError, part_name, plan_configured_part
from tandemscan.pipeline.geometry.units import MM_PER_UNIT


def add_commands(subparsers) -> argparse.ArgumentParser:
    """Add the ``plan`` sub-command to the main CLI's sub-parsers."""
    p = subparsers.add_parser("plan", help="plan AGV stations, scans and tracker transfers for a part")
    p.add_argument("--config", type=Path, help="cell configuration TOML (default: the simulated cell)")
    p.add_argument("--part", type=Path, help="part mesh STL/PLY/OBJ in mm (default: the parametric train nose)")
    p.add_argument("--part-units", choices=sorted(MM_PER_UNIT), help="the unit of the part mesh file (default: mm)")
    p.add_argument("--out", type=Path, help="plan file .toml/.json (default: <job.out_dir>/plan.toml)")
    p.add_argument("--png", type=Path, help="also draw the plan's top view to this PNG")
    p.set_defaults(func=cmd_plan)
    return p


def cmd_plan(args: argparse.Namespace) -> int:
    """Plan the configured part, write the plan, its report and (``--png``) the top view."""
    config = config_from_args(args)
    out = Path(args.out) if args.out else config.job.out_dir / "plan.toml"
    try:
        _, plan = plan_configured_part(config, out.stem)
    except PlanPartError as e:
        raise UsageError(str(e)) from e
    coverage = plan.coverage
    out.parent.mkdir(parents=True, exist_ok=True)
    plan.sequence.plan.save(out)
    report_file = out.with_name(out.stem + "-report.json")
    report = {"plan": str(out), "part": part_name(config), **plan.summary(), "coverage": coverage.as_dict(),
              "tracker_stations_xy_heading": [[round(x, 1), round(y, 1), round(float(np.degrees(h)), 2)]
                                              for x, y, h in plan.tracker_chain]}
    report_file.write_text(json.dumps(report, indent=1), encoding="utf-8")
    if args.png:
        from tandemscan.daemon.cli.plan_figure import draw_plan

        args.png.parent.mkdir(parents=True, exist_ok=True)
        draw_plan(plan, config.installation.T_T_S.matrix(), Path(args.png))
    Console().print(f"[bold]plan[/bold] {out}: {describe(plan)}; report {report_file}")
    return 0


def describe(plan) -> str:
    """One line on a :class:`PartPlan`: counts, tracker solver, coverage and the largest area left out."""
    from tandemscan.pipeline.planning.coverage import REASON_NO_POSE

    s = plan.summary()
    coverage = plan.coverage
    text = (f"{s['scans']} scans at {s['agv_stations']} AGV stations, {s['tracker_stations']} tracker stations "
            f"({s['tracker_solver']}, lower bound {s['tracker_lower_bound']}), {s['transfers']} transfers, "
            f"{s['lift_moves']} column moves; coverage {coverage.coverage_pct:.1f} % of the surface a pose fits "
            f"({coverage.coverage_of_reachable_pct:.1f} % of what the arm reaches); planned in "
            f"{s['plan_seconds']:.1f} s")
    missed = [lo for lo in coverage.left_out if lo.reason != REASON_NO_POSE]
    if missed:
        total = sum(lo.area_mm2 for lo in missed) / 1e6
        top = missed[0]
        text += (f"; {total:.2f} m^2 left out in {len(missed)} areas, largest {top.area_mm2 / 1e6:.2f} m^2 "
                 f"({top.reason}) near station {top.station} at z {top.z_range_mm[0]:.0f}-{top.z_range_mm[1]:.0f} mm")
    return text
