"""A benchmark ended by SIGTERM (``timeout``, a cancelled CI job) unwinds as on an exception, so that the jobs it
keeps in temporary folders (gigabytes for the whole part, tens at full resolution) are removed on the way out."""

from __future__ import annotations

import signal
import sys


def clean_exit_on_sigterm() -> None:
    """From now on SIGTERM raises ``SystemExit(128 + 15)`` in the main thread: ``with`` blocks
    (``tempfile.TemporaryDirectory``) and ``asyncio.run``'s cancellation of its tasks run as they do on an error."""
    signal.signal(signal.SIGTERM, lambda signum, _frame: sys.exit(128 + signum))
