"""``/v1/events``: server-sent events, live and replayed from the journal after a reconnect (docs/daemon.md)."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from typing import Annotated

from fastapi import APIRouter, Header, Query, Request
from fastapi.responses import StreamingResponse
from tandemscan.daemon.api.errors import ApiProblem
from tandemscan.daemon.api.facade import Facade, ServiceFacade
from tandemscan.daemon.api.models import MAX_EVENT_ID, PROBLEM_RESPONSES
from tandemscan.daemon.store.events import sse_text

router = APIRouter(tags=["service"])


@router.get("/v1/events", response_class=StreamingResponse,
            responses={**PROBLEM_RESPONSES, 200: {"content": {"text/event-stream": {}}}})
async def events(
    request: Request, facade: Facade,
    job: Annotated[str | None, Query(max_length=64, description="only this job's events")] = None,
    after: Annotated[int | None, Query(ge=0, le=2**62, description="replay events after this id")] = None,
    last_event_id: Annotated[str | None, Header()] = None,
) -> StreamingResponse:
    """Server-sent events (``state``, ``progress``, ``device``, ``safety``); reconnect with
    ``Last-Event-ID`` (or ``after``) to replay what was missed from the journal. A ``Last-Event-ID`` that
    is not an event id (decimal digits, at most 2**62) is a 400 problem."""
    start = after
    if start is None and last_event_id is not None:
        start = parse_event_id(last_event_id)
    return StreamingResponse(_event_stream(facade, request, job, start), media_type="text/event-stream",
                             headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"})


def parse_event_id(value: str) -> int:
    """An SSE ``Last-Event-ID`` as an event sequence number; :class:`ApiProblem` 400 when it is not one."""
    text = value.strip()
    if not (text.isascii() and text.isdigit() and len(text) <= 19 and int(text) <= MAX_EVENT_ID):
        raise ApiProblem(400, "Malformed Last-Event-ID", f"Last-Event-ID must be an event id (decimal digits up to "
                         f"{MAX_EVENT_ID}); got {value[:40]!r}")
    return int(text)


async def _event_stream(facade: ServiceFacade, request: Request, job: str | None,
                        after: int | None) -> AsyncIterator[str]:
    with facade.subscribe() as sub:  # subscribed first: live events up to the journal's last id are old
        seen, missed = await facade.missed_events(after, job)
        yield missed + ": connected\n\n"
        while True:
            try:
                ev = await asyncio.wait_for(sub.get(), facade.heartbeat_s)
            except TimeoutError:
                if await request.is_disconnected():
                    return
                yield ": ping\n\n"
                continue
            if (ev.seq is not None and ev.seq <= seen) or (job is not None and ev.job_id != job):
                continue
            yield sse_text(ev)
