"""Exponential backoff with jitter: the delays between a device's reconnect tries and a job's retries (seconds)."""

from __future__ import annotations

import random
from collections.abc import Iterator


def backoff_delays(initial_s: float, max_s: float, jitter: float = 0.1,
                   rng: random.Random | None = None) -> Iterator[float]:
    """Exponential backoff: ``initial_s, 2 initial_s, ...`` capped at ``max_s``, each +- ``jitter`` fraction."""
    rng = rng or random.Random()
    delay = initial_s
    while True:
        yield min(delay, max_s) * (1.0 + rng.uniform(-jitter, jitter))
        delay = min(delay * 2.0, max_s)
