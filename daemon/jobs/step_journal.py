"""The runner's journal protocol: where a resumable run commits its steps (``docs/daemon.md``, how a job survives
a crash). The daemon's is :class:`tandemscan.daemon.jobs.journal.StoreJournal` on the job store; a run outside the
daemon has :class:`NoJournal`. Step results are the JSON form of :mod:`tandemscan.daemon.jobs.records`.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Protocol, TypeVar

T = TypeVar("T")


class StepJournal(Protocol):
    """Where a resumable run commits its steps (the daemon's store). ``committed`` maps a step index to
    the result committed for it; a run skips those steps and rebuilds its state from their results. Motion
    is not the journal's: it goes through the session's gate (:class:`~tandemscan.daemon.cell.session.MotionGate`)."""

    committed: dict[int, dict]

    async def run_step(self, idx: int, fn: Callable[[], Awaitable[T]]) -> T:
        """Run one step (pause, cancel and safety stops are handled here)."""
        ...

    async def note(self, idx: int, kind: str, value: dict) -> None:
        """Durably record something of a step under way (the still target's reading before a transfer)."""
        ...

    def notes(self, idx: int) -> dict[str, dict]:
        """What :meth:`note` recorded for a step, by kind."""
        ...

    async def record_resume(self, idx: int, entry: dict) -> None:
        """Durably record how this run resumed at step ``idx`` (one entry per resume, however many there are)."""
        ...

    async def commit(self, idx: int, kind: str, result: dict, scan_file: Path | None = None,
                     scan_points: int = 0) -> None:
        """Commit a step's result (and its fsynced scan file) atomically."""
        ...


class NoJournal:
    """The journal of a run outside the daemon: nothing is resumed (its scans are still written as it goes)."""

    committed: dict[int, dict] = {}

    async def run_step(self, idx: int, fn: Callable[[], Awaitable[T]]) -> T:
        return await fn()

    async def note(self, idx: int, kind: str, value: dict) -> None:
        return None

    def notes(self, idx: int) -> dict[str, dict]:
        return {}

    async def record_resume(self, idx: int, entry: dict) -> None:
        return None

    async def commit(self, idx: int, kind: str, result: dict, scan_file: Path | None = None,
                     scan_points: int = 0) -> None:
        return None
