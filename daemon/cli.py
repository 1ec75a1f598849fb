"""The operator's command line: ``tandemscan <command>``.

Each command is a function taking the parsed arguments and returning an exit status. Bad input (a missing
or invalid config, plan or mesh) prints one clear error line and exits with status 2, never a traceback.
Commands that move hardware (``measure``, ``calibrate``, ``serve``) open a cell session
(:mod:`tandemscan.daemon.session`): the supervisor's safety polling, latch and interlock hold for each; a
safety stop ends the command with one line and status 3.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import sys
from datetime import datetime
from importlib import resources
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from tandemscan.config import CellConfig, ConfigError, load_config

EXIT_USAGE = 2
EXIT_SAFETY_STOP = 3
console = Console(stderr=True)


class UsageError(Exception):
    """Bad input from the operator: reported as one line, exit status 2."""


class SafetyStopped(Exception):
    """A command was stopped by a safety stop: reported as one line, exit status 3."""


def default_plan_path() -> Path:
    """The shipped plan for the default part."""
    return Path(str(resources.files("tandemscan.config").joinpath("plans/default-band.toml")))


def _load_config_with_overrides(args: argparse.Namespace) -> CellConfig:
    config = load_config(args.config)
    part_mesh = getattr(args, "part", None)
    if part_mesh is not None:
        config = config.model_copy(update={"part": config.part.model_copy(update={"mesh": Path(part_mesh)})})
    calibration = getattr(args, "calibration", None)
    if calibration is not None:
        job = config.job.model_copy(update={"installation_source": "calibration", "calibration_file": calibration})
        config = config.model_copy(update={"job": job})
    resolution = getattr(args, "resolution", None)
    if resolution is not None:
        scanner = config.scanner.model_copy(update={"resolution": resolution})
        config = config.model_copy(update={"scanner": scanner})
    return config


def _progress_bar() -> Progress:
    """The progress bar of long commands (on stderr)."""
    return Progress(TextColumn("{task.description:<48}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                    TimeElapsedColumn(), console=console)


def cmd_measure(args: argparse.Namespace) -> int:
    """Run a complete measurement job on the configured cell (the simulated cell by default)."""
    from tandemscan.daemon.installation import InstallationError
    from tandemscan.daemon.runner import JobError, JobRunner
    from tandemscan.pipeline.geometry.part import PartMeshError
    from tandemscan.pipeline.planning.plan import PlanError

    config = _load_config_with_overrides(args)
    out = Path(args.out) if args.out else config.job.out_dir
    job_dir = out / datetime.now().strftime("job-%Y%m%d-%H%M%S")
    try:
        plan = _plan_to_measure(args, config, job_dir)
    except (PlanError, PartMeshError) as e:
        raise UsageError(str(e)) from e
    session = _session(config)

    async def run():
        async with session:
            with _progress_bar() as bar:
                task = bar.add_task("starting", total=len(plan.steps) + 1)
                runner = JobRunner(session, plan, config, job_dir,
                                   lambda p: bar.update(task, completed=p.done, total=p.total, description=p.message))
                return await runner.run()

    result = _run_moving(run, (JobError, InstallationError), f"scans measured so far are in {job_dir / 'scans'}")
    _print_summary(result.report, result.job_dir)
    return 0


def _plan_to_measure(args: argparse.Namespace, config: CellConfig, job_dir: Path):
    """The plan of a ``measure``: ``--plan`` if given (refused when made for another part), else for ``--part``
    a plan made now (saved as ``plan.toml`` in the job folder, and said so), else the shipped band plan."""
    from tandemscan.daemon.plan_cmd import PlanPartError, check_plan_part, describe, plan_configured_part
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
    from tandemscan.daemon.cell import CellBuildError
    from tandemscan.daemon.session import CellSession
    from tandemscan.pipeline.geometry.part import PartMeshError

    try:
        return CellSession(config)
    except (PartMeshError, CellBuildError) as e:
        raise UsageError(str(e)) from e


def _run_moving(run, job_error: type[Exception] | tuple[type[Exception], ...], kept: str):
    """``asyncio.run(run())`` of a command that moves hardware: a safety stop becomes :class:`SafetyStopped`
    (the line says what was kept), a device fault or ``job_error`` a :class:`UsageError`."""
    from tandemscan.drivers.errors import DeviceError, SafetyStop

    try:
        return asyncio.run(run())
    except SafetyStop as e:
        raise SafetyStopped(f"{e}; {kept}") from e
    except (job_error, DeviceError) as e:
        raise UsageError(str(e)) from e


def cmd_calibrate(args: argparse.Namespace) -> int:
    """Calibrate the scanner on its target (hand-eye) from plate scans; writes the calibration file."""
    from tandemscan.daemon.calibrate import CalibrationJobError, run_calibration

    config = _load_config_with_overrides(args)
    session = _session(config)
    out_file = Path(args.out) if args.out else config.calibration.output_file

    async def run():
        async with session:
            with _progress_bar() as bar:
                task = bar.add_task("starting", total=config.calibration.poses)
                return await run_calibration(
                    session, config, out_file, lambda d, t, m: bar.update(task, completed=d, total=t, description=m))

    run = _run_moving(run, CalibrationJobError, f"no calibration written to {out_file}")
    s = run.hand_eye.summary()
    out = Console()
    out.print(f"[bold]calibration[/bold] {run.file}: T_T_S from {run.poses_used} poses ({s['method']}), "
              f"plate-point RMS {s['point_rms_mm']:.4f} mm, 1-sigma {s['sigma_trans_mm']:.4f} mm / "
              f"{s['sigma_rot_deg']:.5f} deg; {len(run.skipped)} views skipped")
    if run.truth_error:
        t = run.truth_error
        out.print(f"  sim truth: calibrated {t['T_T_S_err_mm']:.4f} mm / {t['T_T_S_err_deg']:.5f} deg, "
                  f"nominal was {t['nominal_T_T_S_err_mm']:.3f} mm / {t['nominal_T_T_S_err_deg']:.4f} deg")
    out.print(f"  use it: tandemscan measure --calibration {run.file}")
    return 0


def _print_summary(report: dict, job_dir: Path) -> None:
    out = Console()
    out.print(f"[bold]job[/bold] {job_dir}: {report['scans']} scans, {report['transfers']} coordinate transfers, "
              f"{report['points_cloud']} points in cloud.ply")
    truth = report.get("ground_truth")
    if truth:
        out.print(f"  pose error median {truth['pose_err_mm_median']:.3f} mm / {truth['pose_err_deg_median']:.4f} deg, "
                  f"cloud to part RMS {truth['cloud_rms_mm']:.3f} mm (P95 {truth['cloud_p95_mm']:.3f} mm)")
    inspection = report.get("inspection", {})
    if "as_measured" in inspection:
        tol = inspection["as_measured"]["tolerance"]
        out.print(f"  {tol['in_pct']:.1f} % within [{tol['lower_mm']:+.3f}, {tol['upper_mm']:+.3f}] mm of CAD: "
                  f"{job_dir / inspection['files']['html']}")


def cmd_serve(args: argparse.Namespace) -> int:
    """Run the daemon: devices, job queue and the REST API (``docs/daemon.md``)."""
    from tandemscan.daemon.service import BindRefused, serve

    if not args.verbose:
        logging.getLogger("tandemscan").setLevel(logging.INFO)
    try:
        serve(args.config, args.host, args.port)
    except BindRefused as e:
        raise UsageError(str(e)) from e
    return 0


def _client(args: argparse.Namespace):
    from tandemscan.daemon.client import DaemonClient

    return DaemonClient(args.url)


def cmd_jobs(args: argparse.Namespace) -> int:
    """List the daemon's jobs, newest first."""
    from tandemscan.daemon.client import ClientError

    try:
        with _client(args) as client:
            page = client.jobs(args.state, args.limit)
    except ClientError as e:
        raise UsageError(str(e)) from e
    out = Console()
    for j in page["items"]:
        out.print(f"{j['id']}  {j['state']:<13} {j['progress']:5.1f} %  {j['plan']:<20} {j['created']}")
    out.print(f"{len(page['items'])} of {page['total']} jobs")
    return 0


def cmd_job(args: argparse.Namespace) -> int:
    """``job submit|watch|cancel|pause|resume``: one job on a running daemon."""
    from tandemscan.daemon.client import ClientError

    try:
        with _client(args) as client:
            if args.verb == "submit":
                job = client.submit(args.plan, args.label, args.idempotency_key)
                Console().print(job["id"])
                return _watch(client, job["id"]) if args.watch else 0
            if args.verb == "watch":
                return _watch(client, args.job_id)
            job = client.action(args.job_id, args.verb)
            Console().print(f"{job['id']} {job['state']}")
            return 0
    except ClientError as e:
        raise UsageError(str(e)) from e


def _watch(client, job_id: str) -> int:
    """A live progress bar from the event stream; exit 0 when the job succeeds, 1 otherwise."""
    from tandemscan.daemon.job_state import JobState

    columns = (TextColumn("{task.description:<24}"), BarColumn(), TextColumn("{task.percentage:5.1f} %"))
    with Progress(*columns, TimeElapsedColumn(), console=console) as bar:
        task = bar.add_task(job_id, total=100)
        job = client.watch(
            job_id, lambda pct, j: bar.update(task, completed=pct, description=f"{j['id']} {j['state']}"))
    Console().print(f"{job['id']} {job['state']}" + (f": {job['error']}" if job.get("error") else ""))
    if job["state"] == JobState.SUCCEEDED:
        Console().print(json.dumps(job["figures"]))
    return 0 if job["state"] == JobState.SUCCEEDED else 1


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="tandemscan", description="Two-robot 3D measurement cell")
    parser.add_argument("-v", "--verbose", action="store_true", help="log at debug level")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("measure", help="run a measurement job (simulated cell by default)")
    p.add_argument("--config", type=Path, help="cell configuration TOML (default: the simulated cell)")
    p.add_argument("--plan", type=Path, help="plan TOML/JSON (default: planned now for --part, else the shipped band "
                   "plan of the default part); refused when made for another part")
    p.add_argument("--part", type=Path, help="part mesh STL/PLY/OBJ in mm (default: the parametric train nose)")
    p.add_argument("--resolution", choices=["coarse", "full"], help="simulated scanner resolution")
    p.add_argument("--out", type=Path, help="output folder (default: job.out_dir of the config)")
    p.add_argument("--calibration", type=Path, help="calibration file from `tandemscan calibrate` (sets "
                   "job.installation_source = calibration)")
    p.set_defaults(func=cmd_measure)

    p = sub.add_parser("serve", help="run the daemon with its REST API")
    p.add_argument("--host", help="address to listen on (default: [daemon] host, 127.0.0.1)")
    p.add_argument("--port", type=int, help="port (default: [daemon] port, 8470)")
    p.add_argument("--config", type=Path, help="cell configuration TOML (default: the simulated cell)")
    p.set_defaults(func=cmd_serve)

    url_help = "daemon URL (default: $TANDEMSCAN_URL or http://127.0.0.1:8470)"
    p = sub.add_parser("jobs", help="list the jobs of a running daemon")
    p.add_argument("--url", help=url_help)
    p.add_argument("--state", action="append", help="only jobs in this state (repeatable)")
    p.add_argument("--limit", type=int, default=20)
    p.set_defaults(func=cmd_jobs)

    p = sub.add_parser("job", help="submit, watch, cancel, pause or resume a job on a running daemon")
    p.add_argument("--url", help=url_help)
    verbs = p.add_subparsers(dest="verb", required=True)
    v = verbs.add_parser("submit", help="queue a job (the default plan unless --plan)")
    v.add_argument("--plan", help="a plan name from /v1/plans")
    v.add_argument("--label", help="free text for the MES")
    v.add_argument("--idempotency-key", help="retry-safe key")
    v.add_argument("--watch", action="store_true", help="then follow it with a progress bar")
    for name in ("watch", "cancel", "pause", "resume"):
        v = verbs.add_parser(name, help=f"{name} a job")
        v.add_argument("job_id")
    p.set_defaults(func=cmd_job)

    from tandemscan.daemon.inspect_cmd import register as register_inspect

    register_inspect(sub)

    p = sub.add_parser("calibrate", help="hand-eye calibration from plate scans (simulated cell by default)")
    p.add_argument("--config", type=Path, help="cell configuration TOML (default: the simulated cell)")
    p.add_argument("--out", type=Path, help="calibration file to write (default: calibration.output_file)")
    p.set_defaults(func=cmd_calibrate)

    from tandemscan.daemon.deepmerge_cmd import register as register_deepmerge

    register_deepmerge(sub)

    from tandemscan.daemon.plan_cmd import register as register_plan

    register_plan(sub)
    return parser



def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``tandemscan`` console script."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except (UsageError, ConfigError) as e:
        console.print(f"[red]error:[/red] {e}", highlight=False, soft_wrap=True)
        return EXIT_USAGE
    except SafetyStopped as e:
        console.print(f"[red]safety stop:[/red] {e}", highlight=False, soft_wrap=True)
        return EXIT_SAFETY_STOP
    except KeyboardInterrupt:
        console.print("[yellow]interrupted[/yellow]")
        return 130


if __name__ == "__main__":
    sys.exit(main())
