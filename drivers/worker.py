"""Worker processes of the daemon and its twins: a worker runs below the daemon's priority, dies with its
parent, and stops without waiting.

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
from concurrent.futures import ProcessPoolExecutor

log = logging.getLogger(__name__)

_PR_SET_PDEATHSIG = 1


def init_worker(niceness: int = 0) -> None:
    """A worker's set-up: ``niceness`` added (bulk work yields the CPU to the daemon's event loop), and
    :func:`die_with_parent`."""
    if niceness:
        os.nice(niceness)
    die_with_parent()


def yield_cores(niceness: int) -> None:
    """Add ``niceness`` to every thread of this process (Linux: niceness is a thread's; the threads it starts later
    take their starter's): its work yields the cores to other processes' until it is the only work left. Where the
    threads cannot be listed or reniced nothing changes (logged)."""
    try:
        for tid in map(int, os.listdir("/proc/self/task")):
            try:
                os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + niceness))
            except ProcessLookupError:  # the thread ended meanwhile
                continue
    except OSError as e:
        log.debug("threads not reniced: %s", e)


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


def stop_pool(pool: ProcessPoolExecutor) -> None:
    """Shut ``pool`` down without waiting for a task in flight: its workers are terminated (a correction
    of a full-resolution job can run for minutes; a daemon stopping must not wait for it)."""
    workers = list((getattr(pool, "_processes", None) or {}).values())  # its own handles (CPython 3.8-3.13)
    manager = getattr(pool, "_executor_manager_thread", None)
    pool.shutdown(wait=False, cancel_futures=True)
    for worker in workers:
        if worker.is_alive():
            worker.terminate()
    # the pool's manager thread reaps the workers too; a worker it reaped while this thread waited reads as alive
    # to this thread until the manager has recorded its exit status, so the manager is awaited first
    if manager is not None:
        manager.join(5)
    for worker in workers:
        worker.join(5)
