"""The operator's command line: ``tandemscan <command>`` (the ``tandemscan`` console script, ``python -m
tandemscan.daemon.cli``).

Each command is a function taking the parsed arguments and returning an exit status; every failure ends in one
line on stderr and the exit status of its kind (:mod:`tandemscan.daemon.cli.command`; docs/cli.md, "Exit
status"). The commands, by what they act on: the cell (:mod:`.cell_cmd`: ``measure``, ``calibrate``,
``verify``), the daemon (:mod:`.daemon_cmd`: ``serve``, ``jobs``, ``job``), a part's plan (:mod:`.plan_cmd`),
a cloud's inspection (:mod:`.inspect_cmd`), registration and DeepMerge (:mod:`.registration_cmd`) and OPC UA users
(:mod:`.opcua_cmd`).
"""

from __future__ import annotations

import argparse
import logging

from rich.markup import escape
from tandemscan.daemon.cli import cell_cmd, daemon_cmd, inspect_cmd, opcua_cmd, plan_cmd, registration_cmd
from tandemscan.daemon.cli.command import EXIT_INTERRUPTED, as_command_error, console


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="tandemscan", description="Two-robot 3D measurement cell")
    parser.add_argument("-v", "--verbose", action="store_true", help="log at debug level")
    sub = parser.add_subparsers(dest="command", required=True)
    for commands in (cell_cmd, daemon_cmd, inspect_cmd, registration_cmd, plan_cmd, opcua_cmd):
        commands.add_commands(sub)
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
        failure = as_command_error(e)
        console.print(f"[red]{failure.label}:[/red] {escape(str(failure))}", highlight=False, soft_wrap=True)
        return failure.status

