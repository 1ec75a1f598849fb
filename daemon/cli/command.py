"""What a command of the ``tandemscan`` CLI is: a function of the parsed arguments that returns an exit status,
and how it fails: every failure one line on stderr (:data:`console`) and the exit status of its kind, never a
traceback (docs/cli.md, "Exit status"): bad input (a missing or invalid config, plan, mesh, calibration file, an
unwritable output) 2, a safety stop 3, a device fault 4, a job or calibration that ran but could not produce its
result 5, a defect of the program 70 (its traceback logged with ``-v``). Also what the commands share: the
configuration their options make (:func:`config_from_args`) and their progress bar.
"""

from __future__ import annotations

import argparse
import asyncio
import logging

from rich.console import Console
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


def config_from_args(args: argparse.Namespace) -> CellConfig:
    """The cell configuration of ``--config`` with what the command's options override: ``--part`` (the mesh),
    ``--part-units``, ``--calibration`` (the installation from that file), ``--serial`` and ``--part-number``,
    ``--resolution``."""
    config = load_config(args.config)
    part = {k: v for k, v in (("mesh", getattr(args, "part", None)), ("mesh_units", getattr(args, "part_units", None)))
            if v is not None}
    if part:
        config = config.model_copy(update={"part": config.part.model_copy(update=part)})
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


def progress_bar() -> Progress:
    """The progress bar of long commands (on stderr)."""
    return Progress(TextColumn("{task.description:<48}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                    TimeElapsedColumn(), console=console)


def run_moving(run, kept: str, usage: tuple[type[Exception], ...] = (),
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


def as_command_error(e: Exception) -> CommandError:
    """The one line and status of any exception that ends a command: bad config or an unreadable or unwritable
    file is usage, anything no command expects a :class:`Defect` (its traceback logged at debug level)."""
    if isinstance(e, CommandError):
        return e
    if isinstance(e, ConfigError | OSError):
        return UsageError(str(e))
    log.debug("traceback of the defect", exc_info=e)
    return Defect(f"{type(e).__name__}: {e} (a defect of tandemscan: `tandemscan -v ...` logs its traceback)")


