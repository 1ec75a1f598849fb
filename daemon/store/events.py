"""In-process publish/subscribe of journaled events (state changes, progress, devices, safety).

Every event is written to the store first (so it has a sequence number a client can resume from with
``Last-Event-ID``) and then handed to each live subscriber's bounded queue; a device or safety event the journal
refuses is handed out at once without a sequence number (:mod:`tandemscan.daemon.store.device_events`). A subscriber
that falls more than ``maxsize`` events behind loses the oldest ones and is told so by a ``gap`` marker; it can
re-read them from the journal.
"""

from __future__ import annotations

import asyncio
import json
import logging

from tandemscan.daemon.store.job_store import Event

log = logging.getLogger(__name__)


class Subscription:
    """One subscriber's queue; iterate with ``await sub.get()``."""

    def __init__(self, bus: EventBus, maxsize: int):
        self._bus = bus
        self.queue: asyncio.Queue[Event] = asyncio.Queue(maxsize)
        self.dropped = 0

    def put(self, event: Event) -> None:
        if self.queue.full():
            self.queue.get_nowait()
            self.dropped += 1
        self.queue.put_nowait(event)

    async def get(self) -> Event:
        return await self.queue.get()

    def close(self) -> None:
        self._bus._subs.discard(self)

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class EventBus:
    """Fan-out of events to subscribers in the event loop's thread."""

    def __init__(self) -> None:
        self._subs: set[Subscription] = set()

    def subscribe(self, maxsize: int = 1000) -> Subscription:
        sub = Subscription(self, maxsize)
        self._subs.add(sub)
        return sub

    def publish(self, event: Event) -> None:
        for sub in list(self._subs):
            sub.put(event)

    @property
    def subscribers(self) -> int:
        return len(self._subs)


def sse_text(event: Event) -> str:
    """``event`` as one server-sent event: its id (the journal's sequence number; none for an event the journal
    has not taken), kind and JSON data (the event's fields, its job id and time, Unix s)."""
    data = {"job_id": event.job_id, **event.data, "t_s": event.t_s}
    event_id = "" if event.seq is None else f"id: {event.seq}\n"
    return f"{event_id}event: {event.kind}\ndata: {json.dumps(data)}\n\n"
