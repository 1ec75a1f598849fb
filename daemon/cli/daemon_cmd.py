"""The daemon's commands: ``serve`` runs it (devices, job queue, the REST API), ``jobs`` and ``job`` talk to a
running one through its REST API (:mod:`tandemscan.daemon.cli.client`). docs/cli.md, docs/daemon.md.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from tandemscan.daemon.cli.command import NotStarted, UsageError, console


def add_commands(sub) -> None:
    """Add ``serve``, ``jobs`` and ``job`` to the main CLI's sub-parsers."""
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



def cmd_serve(args: argparse.Namespace) -> int:
    """Run the daemon: devices, job queue and the REST API (``docs/daemon.md``)."""
    from tandemscan.daemon.api.app import serve
    from tandemscan.daemon.api.guard import BindRefused
    from tandemscan.daemon.service import StartupError

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


