"""Set-up shared by the worker processes of the daemon and its twins: a worker dies with its parent.

A daemon killed with SIGKILL (a crash, systemd's watchdog) cannot shut its process pools down; without this
their workers would live on as orphans, holding memory and CPU, and pile up with every restart.
"""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import threading
import time

log = logging.getLogger(__name__)

_PR_SET_PDEATHSIG = 1


def die_with_parent(poll_s: float = 1.0) -> None:
    """Make this process exit when its parent does: ``prctl(PR_SET_PDEATHSIG)`` on Linux, else a thread
    polling the parent's pid every ``poll_s`` seconds."""
    parent = os.getppid()
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) == 0:
            if os.getppid() != parent:  # the parent died before the call
                os._exit(1)
            return
    except (OSError, AttributeError):
        pass

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_s)
        os._exit(1)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()
