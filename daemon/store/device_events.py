"""Device and safety events of the daemon on their way to the event stream, systemd and the journal.

The supervisor's ``on_event(kind, data)`` lands here (in the event loop's thread). A safety event's status line
goes to systemd at once, whatever the journal does. Events are journaled in order by one background writer and
published once journaled (with their sequence number, so that ``Last-Event-ID`` finds them). While the journal
refuses writes (a full disk) an event is published at once without a sequence number (an SSE event without
``id``) and stays queued: the writer retries the oldest every ``retry_s`` seconds and counts each failed write,
and the event enters the journal once it takes writes again (a client that reconnects may then see it twice).
Nothing the writer meets ends it unobserved: an error that is not the storage's is logged and that event dropped
from the queue. See docs/daemon.md, faults.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from dataclasses import dataclass

from tandemscan.daemon.notify import Notifier
from tandemscan.daemon.store.events import EventBus
from tandemscan.daemon.store.job_store import STORAGE_ERRORS, Event, JobStore
from tandemscan.drivers.tasks import cancel_and_wait

log = logging.getLogger(__name__)


@dataclass
class _Queued:
    """An event not journaled yet: its kind, data, time (Unix s) and whether subscribers have it already."""

    kind: str
    data: dict
    t_s: float
    published: bool = False


class DeviceEventJournal:
    """Publishes and journals the supervisor's device and safety events (``emit`` is its ``on_event``)."""

    def __init__(self, store: JobStore, bus: EventBus, notifier: Notifier, retry_s: float = 1.0):
        self.store, self.bus, self.notifier, self.retry_s = store, bus, notifier, retry_s
        self.failed_writes = 0  # journal writes of events refused so far (each retry counts)
        self._queue: deque[_Queued] = deque()
        self._refusing = False  # the last write was refused: new events are published before they are journaled
        self._writer: asyncio.Task | None = None

    @property
    def not_journaled(self) -> int:
        """Events published but not in the journal yet (the journal refused them)."""
        return sum(q.published for q in self._queue)

    def emit(self, kind: str, data: dict) -> None:
        """One event of the supervisor: systemd told at once (safety), queued for the journal, published."""
        if kind == "safety":
            self.notifier.status(f"safety stop: {data['reason']}" if data["latched"] else "safety stop reset")
        queued = _Queued(kind, data, time.time())
        if self._refusing:
            self._publish_unjournaled(queued)
        self._queue.append(queued)
        if self._writer is None or self._writer.done():
            self._writer = asyncio.get_running_loop().create_task(self._write(), name="device-event-journal")

    async def close(self) -> None:
        """Stop the writer; events the journal has not taken by now are logged as lost to it."""
        if self._queue and not self._refusing:
            await asyncio.wait([self._writer], timeout=2.0)  # let a journal that takes writes finish the queue
        await cancel_and_wait(self._writer)
        if self._queue:
            log.warning("%d device events were never journaled (the journal refused them)", len(self._queue))

    def _publish_unjournaled(self, queued: _Queued) -> None:
        self.bus.publish(Event(None, None, queued.kind, queued.data, queued.t_s))
        queued.published = True

    async def _write(self) -> None:
        while self._queue:
            queued = self._queue[0]
            try:
                event = await asyncio.to_thread(self.store.add_event, None, queued.kind, queued.data, queued.t_s)
            except STORAGE_ERRORS as e:
                self.failed_writes += 1
                if not self._refusing:
                    log.error("the journal refuses device events (%s); publishing them unjournaled and retrying", e)
                self._refusing = True
                for waiting in self._queue:
                    if not waiting.published:
                        self._publish_unjournaled(waiting)
                await asyncio.sleep(self.retry_s)
                continue
            except Exception:
                log.exception("device event %s could not be journaled; dropped from the journal", queued.kind)
                if not queued.published:
                    self._publish_unjournaled(queued)
                self._queue.popleft()
                continue
            self._queue.popleft()
            if self._refusing:
                log.info("the journal takes device events again")
            self._refusing = False
            if not queued.published:
                self.bus.publish(event)
