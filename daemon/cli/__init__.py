"""The operator's command line: ``tandemscan <command>``.

Each command is a function taking the parsed arguments and returning an exit status. Every failure ends in one
line on stderr and the exit status of its kind, never a traceback (docs/cli.md, "Exit status"): bad input (a
missing or invalid config, plan, mesh, calibration file, an unwritable output) 2, a safety stop 3, a device fault
4, a job or calibration that ran but could not produce its result 5, a defect of the program 70 (its traceback
logged with ``-v``). Commands that move hardware (``measure``, ``calibrate``, ``serve``) open a cell session
(:mod:`tandemscan.daemon.session`): the supervisor's safety polling, latch and interlock hold for each; their
background workers stop with the command.
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
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from tandemscan.config import CellConfig, ConfigError, load_config

EXIT_USAGE = 2
EXIT_SAFETY_STOP = 3
EXIT_DEVICE_FAULT = 4
EXIT_NOT_COMPLETED = 5
EXIT_INTERNAL = 70
EXIT_RETRY_LATER = 75  # sysexits EX_TEMPFAIL: serve's port is taken (systemd restarts it)
EXIT_NOT_STARTED = 78  # sysexits EX_CONFIG: serve cannot use its state directory or port (no restart)
EXIT_INTERRUPTED = 130
console = Console(stderr=True)
log = logging.getLogger(__name__)


class CommandError(Exception):
    """A command that ends in one line (``label: message``) and its exit ``status``."""

    label = "error"
    status = EXIT_USAGE


class UsageError(CommandError):
    """Bad input from the operator: reported as one line, exit status 2."""


class SafetyStopped(CommandError):
    """A command was stopped by a safety stop: reported as one line, exit status 3."""

    label = "safety stop"
    status = EXIT_SAFETY_STOP


class DeviceFaulted(CommandError):
    """A device timed out, reported a fault, lost the target or could not reach: one line, exit status 4."""

    label = "device fault"
    status = EXIT_DEVICE_FAULT


class NotCompleted(CommandError):
    """A job or calibration ran but could not produce its result: one line, exit status 5."""

    label = "not completed"
    status = EXIT_NOT_COMPLETED


class NotStarted(CommandError):
    """``serve`` could not start (state directory, journal, port): one line, exit status 78, or 75 when waiting
    may help (its port is taken)."""

    label = "daemon not started"

    def __init__(self, message: str, retry: bool):
        super().__init__(message)
        self.status = EXIT_RETRY_LATER if retry else EXIT_NOT_STARTED


class Defect(CommandError):
    """An exception no command expects (a defect of the program): one line, exit status 70; ``-v`` logs its
    traceback."""

    label = "internal error"
    status = EXIT_INTERNAL


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
    identity = {k: v for k, v in (("serial", getattr(args, "serial", None)),
                                  ("part_number", getattr(args, "part_number", None))) if v}
    if identity:
        config = config.model_copy(update={"job": config.job.model_copy(update=identity)})
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
    from tandemscan.daemon.stitcher import LocalWorldMap
    from tandemscan.pipeline.geometry.part import PartMeshError
    from tandemscan.pipeline.planning.plan import PlanError

    config = _load_config_with_overrides(args)
    Console().print(_mounts_line(config), highlight=False, soft_wrap=True)
    out = Path(args.out) if args.out else config.job.out_dir
    job_dir = out / datetime.now().strftime("job-%Y%m%d-%H%M%S")
    try:
        plan = _plan_to_measure(args, config, job_dir)
    except (PlanError, PartMeshError) as e:
        raise UsageError(str(e)) from e
    session = _session(config)
    job_dir.mkdir(parents=True, exist_ok=True)  # an output that cannot be written is bad input, before any motion
    worldmap = LocalWorldMap(config.job.voxel_mm)

    async def run():
        async with session:
            with _progress_bar() as bar:
                task = bar.add_task("starting", total=len(plan.steps) + 1)
                runner = JobRunner(session, plan, config, job_dir,
                                   lambda p: bar.update(task, completed=p.done, total=p.total, description=p.message),
                                   worldmap=worldmap)
                return await runner.run()

    try:  # the pair registration's worker stops with the command, whatever ends it
        result = _run_moving(run, f"scans measured so far are in {job_dir / 'scans'}",
                             usage=(JobError, InstallationError))
    finally:
        worldmap.close()
    _print_summary(result.report, result.job_dir)
    return 0


def _mounts_line(config: CellConfig) -> str:
    """``measure``'s first line: the mounts the job stitches with (``job.installation_source``); on the nominal
    ones a warning that the cell is not calibrated. An unreadable calibration file is a :class:`UsageError`."""
    from tandemscan.daemon.calibration_state import resolve_installation
    from tandemscan.daemon.installation import InstallationError, installation_for_job

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
    from tandemscan.daemon.cli.plan_cmd import PlanPartError, check_plan_part, describe, plan_configured_part
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


def _run_moving(run, kept: str, usage: tuple[type[Exception], ...] = (),
                not_completed: tuple[type[Exception], ...] = ()):
    """``asyncio.run(run())`` of a command that moves hardware, every failure a :class:`CommandError` whose line
    ends in ``kept`` (what was kept): a safety stop :class:`SafetyStopped`, another device error
    :class:`DeviceFaulted`, ``usage`` a :class:`UsageError`, ``not_completed`` or an output that could not be
    written :class:`NotCompleted`, anything else a :class:`Defect` (its traceback logged at debug level)."""
    from tandemscan.drivers.errors import DeviceError, SafetyStop

    try:
        return asyncio.run(run())
    except SafetyStop as e:
        raise SafetyStopped(f"{e}; {kept}") from e
    except DeviceError as e:
        raise DeviceFaulted(f"{e}; {kept}") from e
    except usage as e:
        raise UsageError(f"{e}; {kept}") from e
    except (*not_completed, OSError) as e:
        raise NotCompleted(f"{e}; {kept}") from e
    except Exception as e:
        log.debug("traceback of the defect", exc_info=e)
        raise Defect(f"{type(e).__name__}: {e}; {kept}") from e


def cmd_calibrate(args: argparse.Namespace) -> int:
    """Calibrate the scanner on its target (hand-eye) from plate scans; writes the calibration file."""
    from tandemscan.daemon.calibrate import CalibrationJobError, run_calibration

    config = _load_config_with_overrides(args)
    session = _session(config)
    out_file = Path(args.out) if args.out else config.calibration.output_file
    out_file.parent.mkdir(parents=True, exist_ok=True)  # an output that cannot be written is bad input, before motion

    async def run():
        async with session:
            with _progress_bar() as bar:
                task = bar.add_task("starting", total=config.calibration.poses)
                return await run_calibration(
                    session, config, out_file, lambda d, t, m: bar.update(task, completed=d, total=t, description=m))

    run = _run_moving(run, f"no calibration written to {out_file}", not_completed=(CalibrationJobError,))
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
    from tandemscan.daemon.verify import run_verification

    config = _load_config_with_overrides(args)
    session = _session(config)
    Path(config.verification.output_file).parent.mkdir(parents=True, exist_ok=True)

    async def run():
        async with session:
            with _progress_bar() as bar:
                task = bar.add_task("starting", total=config.verification.views)
                return await run_verification(
                    session, config, lambda d, t, m: bar.update(task, completed=d, total=t, description=m))

    result = _run_moving(run, "no verification recorded")
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


def cmd_serve(args: argparse.Namespace) -> int:
    """Run the daemon: devices, job queue and the REST API (``docs/daemon.md``)."""
    from tandemscan.daemon.service import BindRefused, StartupError, serve

    if not args.verbose:
        logging.getLogger("tandemscan").setLevel(logging.INFO)
    try:
        serve(args.config, args.host, args.port)
    except BindRefused as e:
        raise UsageError(str(e)) from e
    except StartupError as e:
        raise NotStarted(str(e), e.retry) from e
    return 0


def _client(args: argparse.Namespace):
    from tandemscan.daemon.cli.client import DaemonClient

    return DaemonClient(args.url)


def cmd_jobs(args: argparse.Namespace) -> int:
    """List the daemon's jobs, newest first."""
    from tandemscan.daemon.cli.client import ClientError

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
    from tandemscan.daemon.cli.client import ClientError

    try:
        with _client(args) as client:
            if args.verb == "submit":
                job = client.submit(args.plan, args.label, args.idempotency_key, args.part_number, args.serial)
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
    p.add_argument("--serial", help="the measured part's serial number (report, results.qif)")
    p.add_argument("--part-number", help="the measured part's number (default: its inspection template's)")
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
    v.add_argument("--part-number", help="the part's number (OPC UA ProductId; trends are kept per part number)")
    v.add_argument("--serial", help="the part's serial number")
    v.add_argument("--idempotency-key", help="retry-safe key")
    v.add_argument("--watch", action="store_true", help="then follow it with a progress bar")
    for name in ("watch", "cancel", "pause", "resume"):
        v = verbs.add_parser(name, help=f"{name} a job")
        v.add_argument("job_id")
    p.set_defaults(func=cmd_job)

    from tandemscan.daemon.cli.inspect_cmd import register as register_inspect

    register_inspect(sub)

    p = sub.add_parser("calibrate", help="hand-eye calibration from plate scans (simulated cell by default)")
    p.add_argument("--config", type=Path, help="cell configuration TOML (default: the simulated cell)")
    p.add_argument("--out", type=Path, help="calibration file to write (default: calibration.output_file)")
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser("verify", help="interim verification on the calibration plate (VDI/VDE 2634-3 style)")
    p.add_argument("--config", type=Path, help="cell configuration TOML (default: the simulated cell)")
    p.add_argument("--calibration", type=Path, help="calibration file to verify (default: the job's mounts)")
    p.set_defaults(func=cmd_verify)

    from tandemscan.daemon.cli.deepmerge_cmd import register as register_deepmerge

    register_deepmerge(sub)

    from tandemscan.daemon.cli.plan_cmd import register as register_plan

    register_plan(sub)

    from tandemscan.daemon.cli.opcua_cmd import register as register_opcua

    register_opcua(sub)
    return parser



def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``tandemscan`` console script: every failure one line and its exit status."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except KeyboardInterrupt:
        console.print("[yellow]interrupted[/yellow]")
        return EXIT_INTERRUPTED
    except Exception as e:  # noqa: BLE001 - the operator gets one line, never a traceback
        failure = _as_command_error(e)
        console.print(f"[red]{failure.label}:[/red] {escape(str(failure))}", highlight=False, soft_wrap=True)
        return failure.status


def _as_command_error(e: Exception) -> CommandError:
    """The one line and status of any exception that ends a command: bad config or an unreadable or unwritable
    file is usage, anything no command expects a :class:`Defect` (its traceback logged at debug level)."""
    if isinstance(e, CommandError):
        return e
    if isinstance(e, ConfigError | OSError):
        return UsageError(str(e))
    log.debug("traceback of the defect", exc_info=e)
    return Defect(f"{type(e).__name__}: {e} (a defect of tandemscan: `tandemscan -v ...` logs its traceback)")


if __name__ == "__main__":
    sys.exit(main())
