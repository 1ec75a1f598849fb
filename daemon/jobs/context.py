"""What the job manager (:mod:`tandemscan.daemon.jobs.manager`) gives a runner: the job, its journal, the cell, and the
checkpoints where a pause, a cancel or a safety stop takes effect (``docs/daemon.md``, faults).

The runner is ``async runner(ctx: JobContext) -> dict`` (figures of the finished job). It calls
``ctx.run_step(i, fn)`` for each step not yet committed and ``ctx.progress(...)`` as it goes.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

from tandemscan.daemon.cell.supervisor import Supervisor
from tandemscan.daemon.store.events import EventBus
from tandemscan.daemon.store.job_store import JobRecord, JobStore
from tandemscan.drivers.errors import SafetyStop

log = logging.getLogger(__name__)


class JobCancelled(Exception):
    """Raised inside a runner when its job was cancelled."""


class JobControl(Protocol):
    """What a runner's context asks of the job manager (:class:`~tandemscan.daemon.jobs.manager.JobManager`):
    its checkpoints and its event bus."""

    bus: EventBus

    async def checkpoint(self, job_id: str) -> None:
        """Wait while the job is paused; raise :class:`JobCancelled` once it is cancelled."""
        ...

    async def safety_pause(self, job_id: str, reason: str) -> None:
        """Pause the job, while it runs, after a safety stop (``reason``)."""
        ...


@dataclass
class JobContext:
    """What a runner gets: the job, the journal, the devices' supervisor, the cell session (its motion gate and
    observers, :mod:`tandemscan.daemon.cell.session`) and pause/cancel checkpoints."""

    job: JobRecord
    store: JobStore
    supervisor: Supervisor
    manager: JobControl
    cell: Any = None
    config: Any = None
    committed: dict[int, dict] = field(default_factory=dict)
    session: Any = None

    @property
    def resumed(self) -> bool:
        """True when this run continues a job that committed steps before (a restart or a crash)."""
        return bool(self.committed)

    async def checkpoint(self) -> None:
        """Wait while the job is paused; raise :class:`JobCancelled` once it is cancelled."""
        await self.manager.checkpoint(self.job.id)

    async def run_step(self, idx: int, fn: Callable[[], Awaitable[Any]]) -> Any:
        """Run one step: wait at the checkpoint, and after a safety stop pause and run it again on resume."""
        while True:
            await self.checkpoint()
            try:
                return await fn()
            except SafetyStop as e:
                log.warning("job %s step %d halted by safety stop: %s", self.job.id, idx, e)
                await self.manager.safety_pause(self.job.id, str(e))

    async def progress(self, percent: float, current_step: int | None, figures: dict | None = None) -> None:
        """Publish progress (0-100), the step under way and optional figures so far."""
        ev = await asyncio.to_thread(self.store.set_progress, self.job.id, percent, current_step, figures)
        self.manager.bus.publish(ev)


Runner = Callable[[JobContext], Awaitable[dict]]
#: brings the cell back to a known state after a job failed or was cancelled (the job's record, its store)
Abandon = Callable[[JobRecord, JobStore], Awaitable[None]]
