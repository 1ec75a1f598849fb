"""Ending background tasks reliably."""

from __future__ import annotations

import asyncio


async def cancel_and_wait(task: asyncio.Task | None, retry_s: float = 0.1) -> None:
    """Cancel ``task`` and wait until it has ended, cancelling again if a cancellation was swallowed.

    Python 3.11's ``asyncio.wait_for`` (and some libraries) can swallow a cancellation that races with a
    completing operation; a plain ``cancel(); await task`` then waits forever on a task that kept running.
    """
    if task is None:
        return
    while not task.done():
        task.cancel()
        await asyncio.wait([task], timeout=retry_s)
    if not task.cancelled():
        task.exception()  # retrieved: an error in a task being shut down is not news
