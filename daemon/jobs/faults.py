"""Fault classes of a job: what a runner's exception means for the job (``docs/daemon.md``, faults).

- **device** (recoverable): a timeout, a dropped link, an occluded target, a scanner that did not answer, a
  device that reports a fault. The job pauses in ``paused_fault`` with motion stopped; it resumes at the step
  that faulted (every committed step reused), by the operator or the retry policy once the cell is whole.
- **storage** (recoverable once space returns): a scan, the journal or an export could not be written (a full
  disk, a read-only or failing file system). The job pauses in ``paused_fault``; the operator resumes it.
- **operator** (recoverable by the operator, :class:`OperatorDecision`): a scan would be left out beyond ``[job]
  max_scans_left_out``; after a restart the robots are not where the journal left them. The job pauses in
  ``paused_fault`` (never resumed automatically); the reason says what a resume does.
- **unrecoverable** (None): anything else, a pose out of reach, a plan this cell cannot run, a bug. The job fails
  with the reason.
"""

from __future__ import annotations

import errno
import os
import re
import sqlite3
from dataclasses import dataclass
from typing import Literal

from tandemscan.drivers.errors import (
    DeviceError,
    DeviceFault,
    DeviceTimeout,
    NotConnected,
    OutOfReach,
    TargetNotVisible,
)

#: errno values of a file system that cannot take a write now
STORAGE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EIO, errno.EROFS, errno.EFBIG})
#: how libraries that raise without an errno say a write was refused: the C library's texts of
#: :data:`STORAGE_ERRNOS` (formatted into their messages), numpy's ``tofile`` ("Not enough free space to write N
#: bytes", "N requested and M written"), libE57Format through pye57 ("write() failed (ErrorWriteFailed)")
STORAGE_MESSAGE = re.compile("|".join([*(re.escape(os.strerror(e)) for e in sorted(STORAGE_ERRNOS)),
                                       r"Not enough free space", r"\d+ requested and \d+ written",
                                       r"ErrorWriteFailed", r"database or disk is full"]), re.IGNORECASE)
#: what in a storage fault's text says the disk is full (rather than failing or read-only)
_FULL = re.compile(r"full|free space|no space|quota|requested and \d+ written", re.IGNORECASE)


class OperatorDecision(Exception):
    """The job cannot go on without the operator (its text says what to look at and what a resume does)."""


class TooManyScansLeftOut(OperatorDecision):
    """A scan whose target the tracker cannot see would be left out beyond ``[job] max_scans_left_out``."""


class RobotsMovedWhileDown(OperatorDecision):
    """After a restart the robots are not where the journal left them and the tracker cannot tell which moved."""


class ScanSawNothing(OperatorDecision):
    """The first scan after a resume saw nothing where the plan's scanner pose looks at the part."""


@dataclass(frozen=True)
class JobFault:
    """A recoverable fault: its class, the device it came from (device faults) and a one-line reason."""

    kind: Literal["device", "storage", "operator"]
    reason: str
    device: str | None = None


def is_storage_error(exc: BaseException) -> bool:
    """Whether ``exc`` (or an exception it was raised from) is a failed write of the journal or of a file (full
    disk, read-only or failing medium): an SQLite error, an ``OSError`` with one of :data:`STORAGE_ERRNOS`, or any
    exception whose text is one of :data:`STORAGE_MESSAGE` (numpy, pye57 and others raise without an errno)."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, (sqlite3.OperationalError, sqlite3.DatabaseError)):
            return True
        if isinstance(exc, OSError) and exc.errno in STORAGE_ERRNOS:
            return True
        if STORAGE_MESSAGE.search(str(exc)):
            return True
        exc = exc.__cause__ or exc.__context__
    return False


def classify_fault(exc: BaseException) -> JobFault | None:
    """The recoverable fault ``exc`` is, or None when it is unrecoverable (the job fails). A device's error is
    the device's, whatever it was raised from."""
    if not isinstance(exc, DeviceError) and is_storage_error(exc):
        full = getattr(exc, "errno", None) in (errno.ENOSPC, errno.EDQUOT) or _FULL.search(str(exc))
        detail = "disk full" if full else "write failed"
        return JobFault("storage", f"storage fault ({detail}): {type(exc).__name__}: {exc}; free space, then resume")
    if isinstance(exc, OperatorDecision):
        return JobFault("operator", str(exc))
    if isinstance(exc, OutOfReach) or not isinstance(exc, DeviceError):
        return None
    if isinstance(exc, (DeviceTimeout, NotConnected, TargetNotVisible, DeviceFault)):
        return JobFault("device", f"device fault ({exc.device}, {type(exc).__name__}): {exc.reason}", exc.device)
    return None
