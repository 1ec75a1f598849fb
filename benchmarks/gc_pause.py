"""The cyclic garbage collector's full-collection pause in the daemon's process, before and after the session
freezes its heap (``daemon.cell.session.freeze_heap``).

Builds what ``tandemscan serve`` holds before it serves (configuration, the daemon over a fresh state folder,
the web app) and opens the simulated cell's session, which freezes the heap; times ``gc.collect(2)`` (ms, the
stall one full collection puts on the event loop that runs the 50 Hz control period) on the heap as it was
before the freeze (``gc.unfreeze`` first) and after it, median of ``--repeats``, with the objects the
collector tracks. The last line of output is one JSON object.

    nice python benchmarks/gc_pause.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import statistics
import tempfile
import time

from clean_exit import clean_exit_on_sigterm
from results import publish


def full_collection_ms(repeats: int) -> float:
    """Median wall time (ms) of ``gc.collect(2)`` over ``repeats`` collections."""
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        gc.collect(2)
        times.append(1000.0 * (time.perf_counter() - t))
    return round(statistics.median(times), 2)


async def measure(repeats: int) -> dict:
    from tandemscan.config import load_config
    from tandemscan.daemon.api.app import create_app
    from tandemscan.daemon.cell.session import CellSession
    from tandemscan.daemon.service import Daemon

    config = load_config(None)
    with tempfile.TemporaryDirectory() as state:
        create_app(Daemon(config, state, token="x" * 32), manage_lifecycle=True)
        session = CellSession(config)
        await session.open()  # freezes the heap
        try:
            frozen = gc.get_freeze_count()
            after_ms = full_collection_ms(repeats)
            gc.unfreeze()
            tracked = len(gc.get_objects())
            before_ms = full_collection_ms(repeats)
            gc.freeze()
        finally:
            await session.close()
    return {"benchmark": "gc_pause", "objects_tracked": tracked, "objects_frozen_at_open": frozen,
            "full_collection_ms_unfrozen": before_ms, "full_collection_ms_frozen": after_ms, "repeats": repeats}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    publish("gc_pause", asyncio.run(measure(ap.parse_args().repeats)))


if __name__ == "__main__":
    clean_exit_on_sigterm()
    main()
