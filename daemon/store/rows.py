"""What the job store hands out: frozen rows of its journal (jobs, scans, events) and its errors.

Units: mm, rad; times are Unix seconds; ``JobRecord.state`` is a
:class:`~tandemscan.daemon.job_state.JobState` value. See docs/daemon.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path


class StoreError(Exception):
    """The store cannot do what was asked (unknown job, bad state change, corrupt file)."""


class IdempotencyConflict(StoreError):
    """An ``Idempotency-Key`` was reused with a different request body."""


@dataclass(frozen=True)
class JobRecord:
    """One row of ``jobs``: ``progress`` is 0-100, ``current_step`` the index of the step under way."""

    id: str
    seq: int
    state: str
    plan_name: str
    plan: dict
    n_steps: int
    created_s: float
    updated_s: float
    started_s: float | None = None
    finished_s: float | None = None
    progress: float = 0.0
    current_step: int | None = None
    error: str | None = None
    figures: dict = field(default_factory=dict)
    attempts: int = 0
    idempotency_key: str | None = None


@dataclass(frozen=True)
class CommittedScan:
    """One committed raw scan: the file path is relative to the job directory."""

    job_id: str
    step_idx: int
    file: str
    n_points: int
    bytes: int
    t_s: float
    sha256: str | None = None  # of the file's bytes when committed (None: journaled before checksums)


@dataclass(frozen=True)
class PendingScan:
    """A scan file that is on disk and fsynced but not yet committed."""

    step_idx: int
    path: Path
    n_points: int
    bytes: int
    sha256: str


#: the note a damaged scan's step keeps once it is taken back out of the journal (``DamagedScan.entry()``)
DAMAGED_NOTE = "damaged"


@dataclass(frozen=True)
class DamagedScan:
    """A committed scan whose file is missing or not what was committed: its step, its index among the job's
    scans, the file (relative to the job folder) and what is wrong."""

    job_id: str
    step_idx: int
    index: int | None
    file: str
    reason: str

    def entry(self) -> dict:
        return {"job": self.job_id, "step": self.step_idx, "scan_index": self.index, "file": self.file,
                "reason": self.reason}


@dataclass(frozen=True)
class Event:
    """A journaled state change or progress event; ``seq`` grows monotonically (None: an event published while the
    journal refused it, :mod:`tandemscan.daemon.store.device_events`)."""

    seq: int | None
    job_id: str | None
    kind: str
    data: dict
    t_s: float
