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
from tandemscan.config.models import CellConfig
from tandemscan.pipeline.planning.plan import Plan


class PlanPartError(Exception):
    """The part cannot be planned, or a plan does not belong to the part (one line for the operator)."""


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``plan`` sub-command to the main CLI's sub-parsers."""
    p = subparsers.add_parser("plan", help="plan AGV stations, scans and tracker transfers for a part")
    p.add_argument("--config", type=Path, help="cell configuration TOML (default: the simulated cell)")
    p.add_argument("--part", type=Path, help="part mesh STL/PLY/OBJ in mm (default: the parametric train nose)")
    p.add_argument("--out", type=Path, help="plan file .toml/.json (default: <job.out_dir>/plan.toml)")
    p.add_argument("--png", type=Path, help="also draw the plan's top view to this PNG")
    p.set_defaults(func=cmd_plan)
    return p


def part_name(config: CellConfig) -> str:
    """How a plan names its part: the mesh file, or the parametric nose."""
    return str(config.part.mesh) if config.part.mesh else "parametric train nose"


def plan_configured_part(config: CellConfig, name: str):
    """Plan the configured part (mesh file or parametric nose); the tracker chain starts where the tracking robot
    stands (``sim.tracking_start``). Returns the mesh and the :class:`PartPlan`; raises :class:`PlanPartError`."""
    from tandemscan.pipeline.geometry.part import PartMeshError, load_part_mesh
    from tandemscan.pipeline.planning.planner import plan_part
    from tandemscan.pipeline.planning.sequence import SequenceError
    from tandemscan.pipeline.planning.stations import StationPlanningError
    from tandemscan.pipeline.planning.tracker import TrackerPlanningError

    start = config.sim.tracking_start
    try:
        mesh = load_part_mesh(config.part)
        return mesh, plan_part(mesh, config, tracker_start=(start.x_mm, start.y_mm, np.radians(start.heading_deg)),
                               name=name, part=part_name(config))
    except (PartMeshError, StationPlanningError, TrackerPlanningError, SequenceError) as e:
        raise PlanPartError(str(e)) from e


def check_plan_part(plan: Plan, plan_file: Path, config: CellConfig) -> None:
    """Refuse a plan made for another part than the configured mesh (raises :class:`PlanPartError`); a plan that
    does not state its part (older files) is taken as it is."""
    from tandemscan.pipeline.geometry.part import PartMeshError, load_part_mesh, part_identity

    if plan.part_identity is None:
        return
    try:
        mine = part_identity(load_part_mesh(config.part))
    except PartMeshError as e:
        raise PlanPartError(str(e)) from e
    made_for = plan.part_identity
    if mine.sha256 != made_for.sha256:
        raise PlanPartError(
            f"{plan_file}: plan made for another part ({plan.part or 'unnamed'}, bbox {list(made_for.bbox_min_mm)} .. "
            f"{list(made_for.bbox_max_mm)} mm, sha256 {made_for.sha256[:12]}) than {part_name(config)} (bbox "
            f"{list(mine.bbox_min_mm)} .. {list(mine.bbox_max_mm)} mm, sha256 {mine.sha256[:12]}); plan this part "
            "with `tandemscan plan --part MESH` or run `measure --part MESH` without --plan")


def cmd_plan(args: argparse.Namespace) -> int:
    """Plan the configured part, write the plan, its report and (``--png``) the top view."""
    from tandemscan.daemon.cli import UsageError, _load_config_with_overrides

    config = _load_config_with_overrides(args)
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
                                              for x, y, h in plan.tracker_poses]}
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
