"""Stopping background tasks reliably.

Python 3.11's ``asyncio.wait_for`` (and some libraries) can swallow a cancellation that arrives just as the
awaited call completes, so a loop task cancelled once may go on forever and a plain ``cancel(); await task``
never returns. :func:`cancel_and_wait` cancels again until every task has ended.
"""

from __future__ import annotations

import asyncio
import logging

log = logging.getLogger(__name__)


async def cancel_and_wait(*tasks: asyncio.Task | None, retry_s: float = 0.1, attempts: int = 50) -> None:
    """Cancel ``tasks`` (None entries are skipped) and wait until all are done, re-cancelling stragglers
    every ``retry_s`` seconds, at most ``attempts`` times; an error in a task being stopped is only logged."""
    pending = {t for t in tasks if t is not None and not t.done()}
    for _ in range(attempts):
        if not pending:
            return
        for t in pending:
            t.cancel()
        done, pending = await asyncio.wait(pending, timeout=retry_s)
        for t in done:
            if not t.cancelled() and t.exception() is not None:
                log.debug("task %s ended with %r", t.get_name(), t.exception())
    if pending:
        log.error("tasks would not stop: %s", sorted(t.get_name() for t in pending))
