"""The daemon process: store, the cell session (devices, supervisor, simulation), job manager, events and
systemd notification in one object, :class:`Daemon`, which the gateways (:mod:`tandemscan.daemon.api`) put in
front of the MES and operators (:func:`tandemscan.daemon.api.app.serve`).

Environment: ``TANDEMSCAN_STATE_DIR`` (default: systemd's ``$STATE_DIRECTORY``, else ``./state``),
``NOTIFY_SOCKET`` and ``WATCHDOG_USEC`` (set by systemd).

Start-up errors (:class:`StartupError`: the state directory or its journal unusable, the port not bindable) are
found before any device is touched and end ``tandemscan serve`` in one line and their own exit status
(docs/cli.md, "Exit status"), which the systemd unit does not restart on.
"""

from __future__ import annotations

import asyncio
import logging
import os
import shutil
import sqlite3
import tempfile
import time
from collections import deque
from collections.abc import Mapping
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np
from prometheus_client import CollectorRegistry
from tandemscan.config import CellConfig
from tandemscan.daemon.cell.devices import Cell
from tandemscan.daemon.cell.session import CellSession
from tandemscan.daemon.job_state import JobState
from tandemscan.daemon.jobs.journal import journaled_abandon, run_journaled
from tandemscan.daemon.jobs.manager import JobManager, RetryPolicy, Runner
from tandemscan.daemon.metrics import DaemonCollector, timing_histograms
from tandemscan.daemon.notify import Notifier
from tandemscan.daemon.plans import PlanCatalog, part_check
from tandemscan.daemon.store.device_events import DeviceEventJournal
from tandemscan.daemon.store.events import EventBus
from tandemscan.daemon.store.job_store import JobStore
from tandemscan.daemon.store.part_results import PartResults
from tandemscan.drivers.shared_array import remove_stale_blocks
from tandemscan.drivers.tasks import cancel_and_wait

log = logging.getLogger(__name__)

STATE_DIR_ENV = "TANDEMSCAN_STATE_DIR"
#: where a simulated cell keeps its world's state in the state folder (its robots where they stopped)
WORLD_STATE_FILE = "sim_world.json"


class StartupError(Exception):
    """The daemon cannot start: its state directory, its journal or its port (one line for the operator).
    ``retry`` is True where waiting may help (the port is held by another process)."""

    def __init__(self, message: str, retry: bool = False):
        super().__init__(message)
        self.retry = retry


def open_state(state_dir: Path) -> JobStore:
    """The job store in ``state_dir``, once a file could be written there; :class:`StartupError` when the folder
    cannot be made or written (a read-only mount, a file in the way, no permission) or the journal not opened."""
    try:
        state_dir.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=state_dir):
            pass
        return JobStore(state_dir)
    except (OSError, sqlite3.Error) as e:
        raise StartupError(f"state directory {state_dir} is not usable: {type(e).__name__}: {e} (set "
                           f"{STATE_DIR_ENV}, or systemd's StateDirectory=, to a writable folder)") from e


def resolve_state_dir(environ: Mapping[str, str] | None = None) -> Path:
    """``$TANDEMSCAN_STATE_DIR``, else the first of systemd's ``$STATE_DIRECTORY``, else ``./state``."""
    env = os.environ if environ is None else environ
    if env.get(STATE_DIR_ENV):
        return Path(env[STATE_DIR_ENV])
    if env.get("STATE_DIRECTORY"):
        return Path(env["STATE_DIRECTORY"].split(":")[0])
    return Path("state")


def _package_version() -> str:
    try:
        return version("tandemscan")
    except PackageNotFoundError:
        return "0"


def _p99(values) -> float:
    return float(np.percentile(np.fromiter(values, float), 99)) if len(values) else 0.0


class Daemon:
    """Everything the service runs, without the HTTP server (tests drive it directly)."""

    def __init__(self, config: CellConfig, state_dir: Path, runner: Runner | None = None, token: str | None = None,
                 cell: Cell | None = None, notifier: Notifier | None = None, connect_timeout_s: float = 60.0):
        self.config = config
        self.token = token
        self.version = _package_version()
        self.state_dir = Path(state_dir)
        self.store = open_state(self.state_dir)
        self.part_results = PartResults(self.state_dir)  # characteristics by part number and serial
        self.bus = EventBus()
        self.registry = CollectorRegistry()
        self.lag_histogram, lateness_histogram = timing_histograms(self.registry)
        self.notifier = notifier or Notifier()
        self.device_events = DeviceEventJournal(self.store, self.bus, self.notifier)
        self.session = CellSession(config, cell=cell, scan_process=True, state_file=self.state_dir / WORLD_STATE_FILE,
                                   on_event=self.device_events.emit, on_tick_lateness=lateness_histogram.observe,
                                   connect_timeout_s=connect_timeout_s, require_connected=False)
        self.cell, self.supervisor = self.session.cell, self.session.supervisor
        d = config.daemon
        self.manager = JobManager(self.store, self.bus, self.supervisor, runner or run_journaled, self.cell, config,
                                  self.session, RetryPolicy(d.fault_retry_attempts, d.fault_retry_initial_s,
                                                            d.fault_retry_max_s),
                                  journaled_abandon(self.session, config))
        self.plans = PlanCatalog([PlanCatalog.shipped_folder(), self.state_dir / "plans"], config.daemon.default_plan,
                                 check=part_check(config))
        self.sse_heartbeat_s = 15.0
        self.loop_lag_s: deque[float] = deque(maxlen=5000)
        self.job_counts: dict[str, int] = {}  # jobs by state at the last scrape
        self.registry.register(DaemonCollector(self.metrics_snapshot))
        self._tasks: list[asyncio.Task] = []

    # ------------------------------------------------------------ lifecycle

    async def start(self) -> None:
        """Connect the devices, resume an interrupted job, tell systemd we are ready."""
        self._tasks.append(asyncio.create_task(self.notifier.watchdog_loop(), name="sd-watchdog"))
        self._tasks.append(asyncio.create_task(self._lag_monitor(), name="loop-lag"))
        await asyncio.to_thread(remove_stale_blocks)  # scan arrays a killed daemon left in shared memory
        self.notifier.status("connecting devices")
        if await self.session.open():
            status = "ready: all devices connected"
        else:
            status = f"degraded: not connected: {', '.join(self.session.not_connected())} (retrying)"
        await self.manager.start()
        self.notifier.ready(status)
        log.info("tandemscan daemon %s: %s; state in %s", self.version, status, self.state_dir)

    async def close(self) -> None:
        """Stop jobs (they stay resumable), devices and background tasks."""
        self.notifier.stopping()
        await self.manager.close()
        await self.session.close()
        await self.device_events.close()
        await cancel_and_wait(*self._tasks)
        self._tasks.clear()
        await asyncio.to_thread(self.store.close)
        await asyncio.to_thread(self.part_results.close)

    async def _lag_monitor(self, period_s: float = 0.05) -> None:
        """Record how late the event loop wakes a sleeper (s): a blocked loop shows here first."""
        while True:
            t0 = time.perf_counter()
            await asyncio.sleep(period_s)
            self.loop_lag_s.append(max(0.0, time.perf_counter() - t0 - period_s))
            self.lag_histogram.observe(self.loop_lag_s[-1])

    # ------------------------------------------------------------ read models

    def metrics_snapshot(self) -> dict:
        """What the Prometheus collector reports; the job counts are those of the last ``/metrics`` scrape, which
        reads them off the event loop (:meth:`~tandemscan.daemon.api.facade.ServiceFacade.metrics`)."""
        snap = self.supervisor.snapshot()
        return {"jobs": {state: self.job_counts.get(state, 0) for state in JobState}, "devices": snap["devices"],
                "safety": snap["safety"],
                "loop_lag_p99_s": _p99(self.loop_lag_s),
                "control_lateness_p99_s": _p99(self.supervisor.control_lateness_s)}

    def free_bytes(self) -> int:
        """Free space of the file system the state folder is on (bytes)."""
        return shutil.disk_usage(self.state_dir).free

    def bytes_needed(self, n_scans: int) -> int:
        """Disk a job of ``n_scans`` scans needs before it may start: its scans and exports, and the reserve."""
        d = self.config.daemon
        return n_scans * d.scan_bytes_estimate + d.reserve_free_bytes

    def health(self) -> dict:
        """The cell in one line: devices down, the latch, storage; ``degraded`` unless all is well."""
        snap = self.supervisor.snapshot()
        free = self.free_bytes()
        storage_error = self.manager.storage_error
        low = free < self.config.daemon.reserve_free_bytes
        down = self.supervisor.down_devices()
        unjournaled = self.device_events.not_journaled
        damaged = [d.entry() for d in self.manager.damaged_scans]
        remeasuring = any(d["job"] == self.manager.active_id for d in damaged)
        ok = (not down and not snap["safety"]["latched"] and storage_error is None and not low and not unjournaled
              and not remeasuring)
        return {"status": "ok" if ok else "degraded", "devices_connected": not down, "devices_down": down,
                "safety_latched": snap["safety"]["latched"], "active_job": self.manager.active_id,
                "queued_jobs": self.store.list_jobs([JobState.QUEUED], limit=1)[1], "free_bytes": free,
                "storage_low": low, "storage_error": storage_error, "events_not_journaled": unjournaled,
                "event_journal_failures": self.device_events.failed_writes, "damaged_scans": damaged,
                "version": self.version}
