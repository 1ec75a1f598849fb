"""Fault classes of a job: what a runner's exception means for the job (``docs/daemon.md``, faults).

- **device** (recoverable): a timeout, a dropped link, an occluded target, a scanner that did not answer, a
  device that reports a fault. The job pauses in ``paused_fault`` with motion stopped; it resumes at the step
  that faulted (every committed step reused), by the operator or the retry policy once the cell is whole.
- **storage** (recoverable once space returns): a scan, the journal or an export could not be written (a full
  disk, a read-only or failing file system). The job pauses in ``paused_fault``; the operator resumes it.
- **unrecoverable** (None): anything else, a pose out of reach, a plan this cell cannot run, a bug. The job fails
  with the reason.
"""

from __future__ import annotations

import errno
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
#: what a failed write of the journal or a file raises
STORAGE_ERRORS = (OSError, sqlite3.OperationalError, sqlite3.DatabaseError)


@dataclass(frozen=True)
class JobFault:
    """A recoverable fault: its class, the device it came from (device faults) and a one-line reason."""

    kind: Literal["device", "storage"]
    reason: str
    device: str | None = None


def is_storage_error(exc: BaseException) -> bool:
    """Whether ``exc`` is a failed write of the journal or of a file (full disk, read-only or failing medium)."""
    if isinstance(exc, (sqlite3.OperationalError, sqlite3.DatabaseError)):
        return True
    return isinstance(exc, OSError) and exc.errno in STORAGE_ERRNOS


def classify_fault(exc: BaseException) -> JobFault | None:
    """The recoverable fault ``exc`` is, or None when it is unrecoverable (the job fails)."""
    if is_storage_error(exc):
        detail = "disk full" if getattr(exc, "errno", None) == errno.ENOSPC or "full" in str(exc) else "write failed"
        return JobFault("storage", f"storage fault ({detail}): {type(exc).__name__}: {exc}; free space, then resume")
    if isinstance(exc, OutOfReach) or not isinstance(exc, DeviceError):
        return None
    if isinstance(exc, (DeviceTimeout, NotConnected, TargetNotVisible, DeviceFault)):
        return JobFault("device", f"device fault ({exc.device}, {type(exc).__name__}): {exc.reason}", exc.device)
    return None
