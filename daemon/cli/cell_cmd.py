"""The commands that move the cell, each in a cell session of its own (:mod:`tandemscan.daemon.cell.session`: the
supervisor's safety polling, latch and interlock hold for each; their background workers stop with the command):
``measure`` (a whole job), ``calibrate`` (hand-eye from plate scans) and ``verify`` (interim verification on the
plate). docs/cli.md.
"""

from __future__ import annotations

import argparse
import json
from datetime import datetime
from pathlib import Path

from rich.console import Console
from rich.markup import escape
from tandemscan.config import CellConfig
from tandemscan.daemon.cli.command import (
    UsageError,
    config_from_args,
    console,
    progress_bar,
    run_moving,
)
from tandemscan.daemon.cli.plan_cmd import describe
from tandemscan.daemon.plans import PlanPartError, check_plan_part, default_plan_path, plan_configured_part
from tandemscan.pipeline.geometry.units import MM_PER_UNIT


def add_commands(sub) -> None:
    """Add ``measure``, ``calibrate`` and ``verify`` to the main CLI's sub-parsers."""
    p = sub.add_parser("measure", help="run a measurement job (simulated cell by default)")
    p.add_argument("--config", type=Path, help="cell configuration TOML (default: the simulated cell)")
    p.add_argument("--plan", type=Path, help="plan TOML/JSON (default: planned now for --part, else the shipped band "
                   "plan of the default part); refused when made for another part")
    p.add_argument("--part", type=Path, help="part mesh STL/PLY/OBJ in mm (default: the parametric train nose)")
    p.add_argument("--part-units", choices=sorted(MM_PER_UNIT), help="the unit of the part mesh file (default: mm)")
    p.add_argument("--resolution", choices=["coarse", "full"], help="simulated scanner resolution")
    p.add_argument("--out", type=Path, help="output folder (default: job.out_dir of the config)")
    p.add_argument("--calibration", type=Path, help="calibration file from `tandemscan calibrate` (sets "
                   "job.installation_source = calibration)")
    p.add_argument("--serial", help="the measured part's serial number (report, results.qif)")
    p.add_argument("--part-number", help="the measured part's number (default: its inspection template's)")
    p.set_defaults(func=cmd_measure)

    p = sub.add_parser("calibrate", help="hand-eye calibration from plate scans (simulated cell by default)")
    p.add_argument("--config", type=Path, help="cell configuration TOML (default: the simulated cell)")
    p.add_argument("--out", type=Path, help="calibration file to write (default: calibration.output_file)")
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser("verify", help="interim verification on the calibration plate (VDI/VDE 2634-3 style)")
    p.add_argument("--config", type=Path, help="cell configuration TOML (default: the simulated cell)")
    p.add_argument("--calibration", type=Path, help="calibration file to verify (default: the job's mounts)")
    p.set_defaults(func=cmd_verify)



def cmd_measure(args: argparse.Namespace) -> int:
    """Run a complete measurement job on the configured cell (the simulated cell by default)."""
    from tandemscan.daemon.calibration.current import InstallationError
    from tandemscan.daemon.jobs.runner import JobError, JobRunner
    from tandemscan.daemon.jobs.stitcher import LocalWorldMap
    from tandemscan.pipeline.geometry.part import PartMeshError
    from tandemscan.pipeline.planning.plan import PlanError

    config = config_from_args(args)
    Console().print(_mounts_line(config), highlight=False, soft_wrap=True)
    out = Path(args.out) if args.out else config.job.out_dir
    job_dir = out / datetime.now().strftime("job-%Y%m%d-%H%M%S")
    try:
        plan = _plan_to_measure(args, config, job_dir)
    except (PlanError, PartMeshError) as e:
        raise UsageError(str(e)) from e
    session = _session(config)
    job_dir.mkdir(parents=True, exist_ok=True)  # an output that cannot be written is bad input, before any motion
    worldmap = LocalWorldMap(config.job.voxel_mm, config.compute.reads_scan_store)

    async def run():
        async with session:
            with progress_bar() as bar:
                task = bar.add_task("starting", total=len(plan.steps) + 1)
                runner = JobRunner(session, plan, config, job_dir,
                                   lambda p: bar.update(task, completed=p.done, total=p.total, description=p.message),
                                   worldmap=worldmap)
                return await runner.run()

    try:  # the pair registration's worker stops with the command, whatever ends it
        result = run_moving(run, f"scans measured so far are in {job_dir / 'scans'}",
                             usage=(JobError, InstallationError))
    finally:
        worldmap.close()
    _print_summary(result.report, result.job_dir)
    return 0


def _mounts_line(config: CellConfig) -> str:
    """``measure``'s first line: the mounts the job stitches with (``job.installation_source``); on the nominal
    ones a warning that the cell is not calibrated. An unreadable calibration file is a :class:`UsageError`."""
    from tandemscan.daemon.calibration.current import InstallationError, installation_for_job, resolve_installation

    config = resolve_installation(config)
    try:
        installation_for_job(config)
    except InstallationError as e:
        raise UsageError(f"{e} (write one with `tandemscan calibrate`)") from e
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise UsageError(f"calibration file {config.job.calibration_file}: not a calibration "
                         f"({type(e).__name__}: {e})") from e
    if config.job.installation_source == "nominal":
        return ("mounts: nominal (the CAD values of \\[installation]); [bold yellow]warning:[/bold yellow] the cell is "
                "not calibrated, the stitch errs by how far the build is from CAD: run `tandemscan calibrate`, then "
                "`tandemscan measure --calibration FILE`")
    sources = json.loads(Path(config.job.calibration_file).read_text(encoding="utf-8")).get("sources", {})
    calibrated = [k for k, v in sources.items() if v != "nominal"]
    nominal = [k for k, v in sources.items() if v == "nominal"]
    detail = (f"; calibrated {', '.join(calibrated) or 'none'}" + (f", nominal {', '.join(nominal)}" if nominal else "")
              if sources else "")
    return f"mounts: calibration file {escape(str(config.job.calibration_file))}{detail}"


def _plan_to_measure(args: argparse.Namespace, config: CellConfig, job_dir: Path):
    """The plan of a ``measure``: ``--plan`` if given (refused when made for another part), else for ``--part``
    a plan made now (saved as ``plan.toml`` in the job folder, and said so), else the shipped band plan."""
    from tandemscan.pipeline.planning.plan import Plan

    try:
        if args.plan or args.part is None:
            path = Path(args.plan) if args.plan else default_plan_path()
            plan = Plan.load(path)
            check_plan_part(plan, path, config)
            return plan
        _, part_plan = plan_configured_part(config, f"plan of {Path(args.part).name}")
    except PlanPartError as e:
        raise UsageError(str(e)) from e
    job_dir.mkdir(parents=True, exist_ok=True)
    part_plan.sequence.plan.save(job_dir / "plan.toml")
    console.print(f"no --plan given: planned {args.part}: {describe(part_plan)}; plan {job_dir / 'plan.toml'}",
                  highlight=False, soft_wrap=True)
    return part_plan.sequence.plan


def _session(config: CellConfig):
    """The cell session of a command (devices built, nothing connected yet); bad device config is usage."""
    from tandemscan.daemon.cell.devices import CellBuildError
    from tandemscan.daemon.cell.session import CellSession
    from tandemscan.pipeline.geometry.part import PartMeshError

    try:
        return CellSession(config)
    except (PartMeshError, CellBuildError) as e:
        raise UsageError(str(e)) from e


def cmd_calibrate(args: argparse.Namespace) -> int:
    """Calibrate the scanner on its target (hand-eye) from plate scans; writes the calibration file."""
    from tandemscan.daemon.calibration.calibrate import CalibrationJobError, run_calibration

    config = config_from_args(args)
    session = _session(config)
    out_file = Path(args.out) if args.out else config.calibration.output_file
    out_file.parent.mkdir(parents=True, exist_ok=True)  # an output that cannot be written is bad input, before motion

    async def run():
        async with session:
            with progress_bar() as bar:
                task = bar.add_task("starting", total=config.calibration.poses)
                return await run_calibration(
                    session, config, out_file, lambda d, t, m: bar.update(task, completed=d, total=t, description=m))

    run = run_moving(run, f"no calibration written to {out_file}", not_completed=(CalibrationJobError,))
    s = run.hand_eye.summary()
    out = Console()
    out.print(f"[bold]calibration[/bold] {run.file}: T_T_S from {run.poses_used} poses ({s['method']}), "
              f"plate-point RMS {s['point_rms_mm']:.4f} mm, 1-sigma {s['sigma_trans_mm']:.4f} mm / "
              f"{s['sigma_rot_deg']:.5f} deg; {len(run.skipped)} views skipped")
    if run.truth_error:
        t = run.truth_error
        out.print(f"  sim truth: calibrated {t['T_T_S_err_mm']:.4f} mm / {t['T_T_S_err_deg']:.5f} deg, "
                  f"nominal was {t['nominal_T_T_S_err_mm']:.3f} mm / {t['nominal_T_T_S_err_deg']:.4f} deg")
    if Path(run.file).resolve() == Path(config.calibration.output_file).resolve():
        out.print("  the cell's current calibration: jobs with installation_source = \"current\" (the default) use it "
                  f"until the cell configuration changes or it is {config.calibration.max_age_h:g} h old")
    else:
        out.print(f"  use it: tandemscan measure --calibration {run.file}")
    return 0


def cmd_verify(args: argparse.Namespace) -> int:
    """Interim verification (VDI/VDE 2634-3 style): the plate's spheres through the whole chain; 0 when it
    passes, 1 when an error is beyond its MPE (recorded either way)."""
    from tandemscan.daemon.calibration.verify import run_verification

    config = config_from_args(args)
    session = _session(config)
    Path(config.verification.output_file).parent.mkdir(parents=True, exist_ok=True)

    async def run():
        async with session:
            with progress_bar() as bar:
                task = bar.add_task("starting", total=config.verification.views)
                return await run_verification(
                    session, config, lambda d, t, m: bar.update(task, completed=d, total=t, description=m))

    result = run_moving(run, "no verification recorded")
    Console().print(f"[bold]verification[/bold] {result.summary()}; recorded in {config.verification.output_file}")
    for why in result.failures:
        Console().print(f"  [bold red]fail:[/bold red] {why}")
    return 0 if result.result == "pass" else 1


def _print_summary(report: dict, job_dir: Path) -> None:
    out = Console()
    out.print(f"[bold]job[/bold] {job_dir}: {report['scans']} scans, {report['transfers']} coordinate transfers, "
              f"{report['points_cloud']} points in cloud.ply")
    truth = report.get("ground_truth")
    if truth:
        out.print(f"  pose error median {truth['pose_err_mm_median']:.3f} mm / {truth['pose_err_deg_median']:.4f} deg, "
                  f"cloud to part RMS {truth['cloud_rms_mm']:.3f} mm (P95 {truth['cloud_p95_mm']:.3f} mm)")
    coverage = report.get("coverage")
    if coverage:
        left = coverage["left_out"]
        out.print(f"  coverage of the {coverage['of']}: planned {_pct(coverage['planned_pct'])}, measured "
                  f"{_pct(coverage['measured_pct'])}; {len(left)} areas left out"
                  + (f", {sum(a['area_m2'] for a in left):.2f} m^2" if left else ""), highlight=False)
    inspection = report.get("inspection", {})
    if "as_measured" in inspection:
        tol = inspection["as_measured"]["tolerance"]
        out.print(f"  {tol['in_pct']:.1f} % within [{tol['lower_mm']:+.3f}, {tol['upper_mm']:+.3f}] mm of CAD: "
                  f"{job_dir / inspection['files']['html']}")
    elif "reason" in inspection:  # the alignment to CAD failed: verdict indeterminate
        out.print(f"  inspection indeterminate: {inspection['reason']}: {job_dir / inspection['files']['html']}",
                  highlight=False, markup=False)


def _pct(value: float | None) -> str:
    return "unknown" if value is None else f"{value:.1f} %"


