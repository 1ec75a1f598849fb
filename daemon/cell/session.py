"""The cell session: what every command that moves hardware opens (``measure``, ``calibrate``, ``serve``).

Opening a :class:`CellSession` starts the simulation where the cell has one (it restores the saved world
state and starts the hardware-in-the-loop emulators), then the :class:`~tandemscan.daemon.cell.supervisor.Supervisor`:
it connects every device (a failed one retries with backoff), polls the safety I/O every control period
(``safety.poll_period_s``, 20 ms = 50 Hz) and latches a safety stop. The session is the cell's
:class:`MotionGate`: a motion is refused unless the session is open and the latch is clear, and the
supervisor refuses to start one robot while the other moves; inside the block the gate hands out the robot's
motion commands (:mod:`tandemscan.daemon.cell.motion`), nowhere else reachable. Runs get the gate; a journal (pause,
cancel, durable commits) is the daemon's business, separate from it (``docs/daemon.md``).
"""

from __future__ import annotations

import gc
import logging
from collections.abc import AsyncIterator, Callable
from contextlib import AbstractAsyncContextManager, asynccontextmanager
from pathlib import Path
from typing import Literal, Protocol, overload

from tandemscan.config.models import CellConfig
from tandemscan.daemon.cell.devices import Cell, build_cell
from tandemscan.daemon.cell.motion import MeasureRobot, Robot, TrackingRobot
from tandemscan.daemon.cell.observer import CalibrationObserver, JobObserver
from tandemscan.daemon.cell.supervisor import EventSink, Supervisor
from tandemscan.drivers.errors import DeviceError, SafetyStop

log = logging.getLogger(__name__)


def freeze_heap() -> None:
    """Collect cyclic garbage once, then take every object alive now out of the cyclic collector's scans
    (``gc.freeze``) until the session closes (``gc.unfreeze`` in :meth:`CellSession.close`). The imported stack
    (NumPy, pydantic, the web app, the drivers: about 150 k objects in the daemon) is otherwise scanned by every
    full collection, an 80 ms stall of the event loop that runs the 20 ms control period
    (``benchmarks/gc_pause.py``). Frozen objects are still freed when their last reference goes; a reference
    cycle among them waits for the thaw at close."""
    gc.collect()
    gc.freeze()


class MotionGate(Protocol):
    """Every motion of a robot runs inside ``async with gate.motion(Robot.X) as robot``, through ``robot``."""

    @overload
    def motion(self, robot: Literal[Robot.MEASURE]) -> AbstractAsyncContextManager[MeasureRobot]: ...

    @overload
    def motion(self, robot: Literal[Robot.TRACKING]) -> AbstractAsyncContextManager[TrackingRobot]: ...

    def motion(self, robot: Robot) -> AbstractAsyncContextManager[MeasureRobot | TrackingRobot]:
        """Refuses (:class:`SafetyStop`, :class:`~tandemscan.daemon.cell.supervisor.MotionInterlock`, or
        :class:`~tandemscan.drivers.errors.NotConnected` while one of the robot's devices is down) or runs the
        block with the robot's motion handle, revoked when the block ends; a safety stop during it interrupts
        it with :class:`SafetyStop`."""
        ...


class DevicesNotConnected(DeviceError):
    """The session could not connect every device within its connect timeout."""


class CellSession:
    """One open cell: devices, supervisor and simulation, and the motion gate over them.

    ``require_connected``: :meth:`open` raises :class:`DevicesNotConnected` unless every device connects
    within ``connect_timeout_s`` (a command run); otherwise the session opens degraded and the supervisor
    keeps reconnecting (the daemon). ``cell``: devices already built (tests); default: from ``config``.
    """

    def __init__(self, config: CellConfig, *, cell: Cell | None = None, scan_process: bool = False,
                 state_file: Path | None = None, on_event: EventSink | None = None,
                 on_tick_lateness: Callable[[float], None] | None = None, connect_timeout_s: float = 60.0,
                 require_connected: bool = True):
        """Eight parameters: the configuration, then keyword-only options each with its default (the devices
        already built, where the simulation keeps its state and scans, the two sinks the supervisor reports
        to, how long and whether to wait for every device)."""
        self.config = config
        self.cell = cell if cell is not None else build_cell(config, scan_process=scan_process, state_file=state_file)
        d = config.daemon
        self.supervisor = Supervisor(
            self.cell.devices(), self.cell.motion_devices(), self.cell.safety,
            control_period_s=config.safety.poll_period_s, health_period_s=d.health_period_s,
            device_timeout_s=d.device_timeout_s, reconnect_initial_s=d.reconnect_initial_s,
            reconnect_max_s=d.reconnect_max_s, on_event=on_event, on_tick_lateness=on_tick_lateness)
        self.connect_timeout_s = connect_timeout_s
        self.require_connected = require_connected
        self.active = False

    async def open(self) -> bool:
        """Start the simulation and the supervisor; returns whether every device connected in time. The heap
        is frozen first (:func:`freeze_heap`), before the supervisor's control loop runs."""
        freeze_heap()
        if self.cell.simulation is not None:
            await self.cell.simulation.start()
        try:
            await self.supervisor.start()
            try:
                await self.supervisor.wait_connected(self.connect_timeout_s)
            except TimeoutError:
                missing = ", ".join(self.not_connected())
                if self.require_connected:
                    errors = "; ".join(f"{h.name}: {h.last_error}" for h in self.supervisor.health.values()
                                       if not h.connected and h.last_error)
                    raise DevicesNotConnected("cell", f"not connected: {missing} ({errors})") from None
                log.warning("session open degraded: not connected: %s (retrying)", missing)
        except BaseException:
            await self._close_devices()
            raise
        self.active = True
        return self.supervisor.all_connected

    def not_connected(self) -> list[str]:
        """Names of the devices not connected now."""
        return [h.name for h in self.supervisor.health.values() if not h.connected]

    async def close(self) -> None:
        """Stop every motion, close the supervisor and devices, then the simulation."""
        self.active = False
        await self.supervisor.halt()
        await self._close_devices()

    async def _close_devices(self) -> None:
        await self.supervisor.close()
        if self.cell.simulation is not None:
            await self.cell.simulation.stop()
        gc.unfreeze()  # the session's own reference cycles are collectable again

    async def __aenter__(self) -> CellSession:
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    @property
    def gate(self) -> MotionGate:
        return self

    @asynccontextmanager
    async def motion(self, robot: Robot) -> AsyncIterator[MeasureRobot | TrackingRobot]:
        """The gate: refused unless the session is open; then the supervisor's latch, device health and
        interlock; the block gets the robot's motion handle, revoked when it ends."""
        if not self.active:
            raise SafetyStop("session", f"motion of the {robot} robot refused: the cell session is not open")
        async with self.supervisor.motion(robot):
            handle, views = self.cell._movers.grant(robot)  # the one reader of the raw movers (daemon/cell/motion.py)
            try:
                yield handle
            finally:
                for view in views:
                    view.revoke("its motion block has ended")

    def job_observer(self, job_key: str, resumed: bool = False) -> JobObserver | None:
        """The simulation's observer of one job; None on a real cell."""
        sim = self.cell.simulation
        return None if sim is None else sim.job_observer(job_key, resumed)

    def calibration_observer(self) -> CalibrationObserver | None:
        """The simulation's observer of a calibration job; None on a real cell."""
        sim = self.cell.simulation
        return None if sim is None else sim.calibration_observer()
