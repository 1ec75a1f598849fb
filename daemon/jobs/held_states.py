"""Job state changes the journal cannot take (a full disk): held in memory, served as the job's state and written
as soon as the journal takes them again (``docs/daemon.md``, faults)."""

from __future__ import annotations

import asyncio
import dataclasses
import logging

from tandemscan.daemon.store.events import EventBus
from tandemscan.daemon.store.job_store import STORAGE_ERRORS, JobRecord, JobStore
from tandemscan.drivers.tasks import cancel_and_wait

log = logging.getLogger(__name__)


class HeldStates:
    """The state changes of ``store``'s jobs not journaled yet, each ``(state, error)``; written (and published on
    ``bus``) by a background task every ``period_s`` seconds until the journal takes them."""

    def __init__(self, store: JobStore, bus: EventBus, period_s: float = 1.0):
        self.store, self.bus, self.period_s = store, bus, period_s
        self._held: dict[str, tuple[str, str | None]] = {}
        self._flusher: asyncio.Task | None = None

    def current(self, job: JobRecord) -> JobRecord:
        """``job`` (read from the store) with its held state change applied."""
        held = self._held.get(job.id)
        return job if held is None else dataclasses.replace(job, state=held[0], error=held[1])

    @property
    def error(self) -> str | None:
        """Why a state change is held now; None when all are written."""
        return next((f"job {j} is {st} but the journal cannot record it" for j, (st, _) in self._held.items()), None)

    def hold(self, job_id: str, state: str, error: str | None) -> None:
        """Hold a state change the journal refused, and write it once the journal takes it."""
        self._held[job_id] = (state, error)
        if self._flusher is None or self._flusher.done():
            self._flusher = asyncio.create_task(self._flush(), name="state-flusher")

    def written(self, job_id: str) -> None:
        """A later state change of ``job_id`` was journaled: nothing of it is held any more."""
        self._held.pop(job_id, None)

    async def close(self) -> None:
        await cancel_and_wait(self._flusher)

    async def _flush(self) -> None:
        while self._held:
            await asyncio.sleep(self.period_s)
            for job_id, (state, error) in list(self._held.items()):
                try:
                    _, event = await asyncio.to_thread(self.store.set_state, job_id, state, error)
                except STORAGE_ERRORS:
                    continue
                if self._held.get(job_id) == (state, error):
                    del self._held[job_id]
                self.bus.publish(event)
                log.info("job %s: held state %s journaled", job_id, state)
