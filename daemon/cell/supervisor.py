"""The supervisor: device connections and health, reconnect with backoff, and the cell's safety.

Safety rules enforced here (not only in plans):

- A safety stop from any source (safety I/O polled every control period, a device raising
  :class:`SafetyStop`, an operator) is *latched*: every motion device gets ``stop()`` and every motion in
  flight is interrupted with :class:`SafetyStop` within one control period. Motion is refused while latched;
  :meth:`Supervisor.reset_safety` clears the latch only when the inputs allow motion again.
- Health is the truth: a device counts as down when its link failed *or* its own status says ``fault``; a down
  device is reconnected (closed and connected again) with exponential backoff until its status is clean.
- Never both robots moving: every motion goes through :meth:`Supervisor.motion`, which refuses to start a
  robot while another one is moving (:class:`MotionInterlock`).

Times are seconds (monotonic clock).
"""

from __future__ import annotations

import asyncio
import logging
import random
import time
from collections import deque
from collections.abc import AsyncIterator, Callable, Iterator, Mapping, Sequence
from contextlib import asynccontextmanager
from dataclasses import dataclass, field

from tandemscan.daemon.jsonable import jsonable
from tandemscan.drivers.errors import DeviceError, NotConnected, SafetyStop
from tandemscan.drivers.interfaces import Device, DeviceState, PushesSafetyChanges, SafetyIO, SafetyState
from tandemscan.drivers.tasks import cancel_and_wait

log = logging.getLogger(__name__)

# Consecutive safety I/O reads that fail before the latch (control ticks one period apart, 20 ms by default, and
# any read woken by a pushed change between them).
# One failed read can be the supervisor's own event loop stalled (a long garbage collection, a starved CPU):
# the poll's reply and the read were delayed alike, and the next tick reads the reply. A state that forbids
# motion latches at its first reading.
UNREADABLE_TICKS = 2


class MotionInterlock(DeviceError):
    """A robot was asked to move while the other one is moving."""


@dataclass
class _Motion:
    robot: str
    task: asyncio.Task
    tripped: bool = False


EventSink = Callable[[str, dict], None]


class Supervisor:
    """Owns the devices of one cell: connection, health, safety latch and the motion gate.

    ``robots`` maps a robot name to its motion devices (each has an async ``stop()``); ``safety`` is the
    cell's safety I/O, polled every ``control_period_s``. ``on_event(kind, data)`` receives device and
    safety changes (kinds ``device`` and ``safety``).
    """

    def __init__(
        self, devices: Sequence[Device], robots: Mapping[str, Sequence[Device]], safety: SafetyIO | None,
        *, control_period_s: float = 0.02, health_period_s: float = 1.0, device_timeout_s: float = 2.0,
        reconnect_initial_s: float = 0.5, reconnect_max_s: float = 30.0, on_event: EventSink | None = None,
        on_tick_lateness: Callable[[float], None] | None = None,
    ):
        """Ten parameters: what it supervises (the devices, the robots' motion devices, the safety I/O), then
        keyword-only settings each with its default: its five periods and timeouts (``[safety]``, ``[daemon]``)
        and the two sinks it reports to."""
        self.devices = {d.name: d for d in devices}
        self.robots = {r: list(ds) for r, ds in robots.items()}
        self.safety_io = safety
        self.control_period_s = control_period_s
        self.health_period_s = health_period_s
        self.device_timeout_s = device_timeout_s
        self.reconnect_initial_s = reconnect_initial_s
        self.reconnect_max_s = reconnect_max_s
        self.on_event = on_event or (lambda kind, data: None)
        self.health = {name: DeviceHealth(name) for name in self.devices}
        self.latched_reason: str | None = None
        self.safety_inputs: SafetyState | None = None  # the control loop's last reading
        self.safety_listeners: list[Callable[[str], None]] = []
        self.connection_listeners: list[Callable[[bool], None]] = []  # called with all_connected on each change
        self.control_lateness_s: deque[float] = deque(maxlen=5000)
        self.on_tick_lateness = on_tick_lateness or (lambda s: None)  # each control tick's lateness (s)
        self._motions: list[_Motion] = []
        self._tasks: list[asyncio.Task] = []
        self._reconnecting: dict[str, asyncio.Task] = {}
        self._all_connected = asyncio.Event()
        self._safety_wake = asyncio.Event()  # set at a control tick, or by a pushed state that forbids motion
        self._safety_pushed = False
        if isinstance(safety, PushesSafetyChanges):  # once: a session opened again keeps its supervisor
            safety.add_listener(self._on_safety_change)

    # ------------------------------------------------------------ lifecycle

    async def start(self) -> None:
        """Connect every device (failures retry in the background) and start health and safety loops."""
        await asyncio.gather(*(self._connect_once(name) for name in self.devices))
        for name, h in self.health.items():
            if not h.up:
                self._schedule_reconnect(name)
        self._update_all_connected()
        self._tasks.append(asyncio.create_task(self._health_loop(), name="supervisor-health"))
        if self.safety_io is not None:
            self._tasks.append(asyncio.create_task(self._safety_loop(), name="supervisor-safety"))

    async def wait_connected(self, timeout_s: float | None = None) -> None:
        """Return once every device is connected (raises TimeoutError after ``timeout_s``)."""
        await asyncio.wait_for(self._all_connected.wait(), timeout_s)

    @property
    def all_connected(self) -> bool:
        return self._all_connected.is_set()

    async def close(self) -> None:
        """Stop the loops and close every device."""
        await cancel_and_wait(*self._tasks, *self._reconnecting.values())
        self._tasks.clear()
        self._reconnecting.clear()
        for d in self.devices.values():
            try:
                await asyncio.wait_for(d.close(), self.device_timeout_s)
            except (DeviceError, TimeoutError, OSError) as e:
                log.warning("closing %s: %s", d.name, e)

    # ------------------------------------------------------------ connection and health

    async def _connect_once(self, name: str) -> bool:
        h = self.health[name]
        try:
            await asyncio.wait_for(self.devices[name].connect(), self.device_timeout_s)
            status = await asyncio.wait_for(self.devices[name].status(), self.device_timeout_s)
        except (DeviceError, TimeoutError, OSError) as e:
            self._set_health(name, connected=False, state=DeviceState.DISCONNECTED,
                             last_error=str(e) or type(e).__name__)
            return False
        self._set_health(name, connected=status.connected, state=status.state, detail=jsonable(dict(status.detail)),
                         last_error=None if status.connected else h.last_error)
        return h.up

    def _schedule_reconnect(self, name: str) -> None:
        if name not in self._reconnecting or self._reconnecting[name].done():
            self._reconnecting[name] = asyncio.create_task(self._reconnect(name), name=f"reconnect-{name}")

    async def _reconnect(self, name: str) -> None:
        for delay in backoff_delays(self.reconnect_initial_s, self.reconnect_max_s):
            self.health[name].next_retry_s = time.monotonic() + delay
            await asyncio.sleep(delay)
            self.health[name].reconnects += 1
            log.info("reconnecting %s (attempt %d)", name, self.health[name].reconnects)
            if await self._connect_once(name):
                self.health[name].next_retry_s = None
                self._update_all_connected()
                return

    async def _health_loop(self) -> None:
        while True:
            await asyncio.sleep(self.health_period_s)
            await asyncio.gather(*(self.poll_device(n) for n in self.devices if n not in self._busy_reconnects()))

    def _busy_reconnects(self) -> set[str]:
        return {n for n, t in self._reconnecting.items() if not t.done()}

    async def poll_device(self, name: str) -> DeviceHealth:
        """Read one device's status now; a failure or a dropped link starts a reconnect with backoff."""
        try:
            s = await asyncio.wait_for(self.devices[name].status(), self.device_timeout_s)
        except (DeviceError, TimeoutError, OSError) as e:
            self._set_health(name, connected=False, state=DeviceState.FAULT, last_error=str(e) or type(e).__name__)
        else:
            self._set_health(name, connected=s.connected, state=s.state, detail=jsonable(dict(s.detail)),
                             **({"last_error": fault_reason(s.detail)} if s.state == DeviceState.FAULT else {}))
        if not self.health[name].up:
            self._schedule_reconnect(name)
        self._update_all_connected()
        return self.health[name]

    def _set_health(self, name: str, **changes: object) -> None:
        h = self.health[name]
        before = (h.connected, h.state, h.last_error)
        for k, v in changes.items():
            setattr(h, k, v)
        if (h.connected, h.state, h.last_error) != before:
            self.on_event("device", h.as_dict())

    def _update_all_connected(self) -> None:
        whole = all(h.up for h in self.health.values())
        if whole == self._all_connected.is_set():
            return
        if whole:
            self._all_connected.set()
        else:
            self._all_connected.clear()
        for listener in list(self.connection_listeners):
            listener(whole)

    def down_devices(self) -> list[str]:
        """Names of the devices down now (not connected, or their status says fault)."""
        return [h.name for h in self.health.values() if not h.up]

    # ------------------------------------------------------------ safety

    def _on_safety_change(self, state: SafetyState) -> None:
        """A change the safety I/O pushed as its poll's reply arrived: one that forbids motion is read at once."""
        if not state.motion_allowed:
            self._safety_pushed = True
            self._safety_wake.set()

    async def _wait_for_tick(self, tick_t: float) -> bool:
        """Sleep until ``tick_t`` (``time.monotonic()``, s) or until the safety I/O pushes a state that forbids
        motion (:meth:`_on_safety_change`); True at the tick, False when woken before it."""
        if not self._safety_pushed:
            timer = asyncio.get_running_loop().call_later(max(0.0, tick_t - time.monotonic()), self._safety_wake.set)
            try:
                await self._safety_wake.wait()
            finally:
                timer.cancel()
        self._safety_wake.clear()
        pushed, self._safety_pushed = self._safety_pushed, False
        return not pushed or time.monotonic() >= tick_t

    async def _safety_loop(self) -> None:
        """Read the safety I/O every control period and when it pushes a change (:meth:`_wait_for_tick`); latch
        on a state that forbids motion at once, and on an unreadable safety I/O when the next read fails too
        (:data:`UNREADABLE_TICKS`)."""
        period = self.control_period_s
        next_t = time.monotonic() + period
        unreadable_ticks = 0
        while True:
            if await self._wait_for_tick(next_t):
                now = time.monotonic()
                self.control_lateness_s.append(max(0.0, now - next_t))
                self.on_tick_lateness(self.control_lateness_s[-1])
                next_t = max(next_t + period, now)
            try:
                state = await asyncio.wait_for(self.safety_io.read(), period * 5)
            except (DeviceError, TimeoutError, OSError) as e:
                unreadable_ticks += 1
                reason = f"safety I/O unreadable: {str(e) or type(e).__name__}"
                if unreadable_ticks >= UNREADABLE_TICKS:
                    await self.trip(reason)
                else:
                    log.warning("%s (read again next tick)", reason)
                continue
            unreadable_ticks = 0
            self.safety_inputs = state
            if not state.motion_allowed:
                await self.trip("e-stop pressed" if state.estop else "light curtain broken")

    async def trip(self, reason: str) -> None:
        """Latch a safety stop: stop every motion device and interrupt every motion in flight."""
        first = self.latched_reason is None
        if first:
            self.latched_reason = reason
            log.error("safety stop latched: %s", reason)
        tripped = False
        for m in self._motions:
            if not m.tripped:
                m.tripped = True
                m.task.cancel(f"safety stop: {reason}")
                tripped = True
        if not (first or tripped):
            return  # latched, nothing moving: every motion device was stopped when it latched
        if first:  # both only schedule work: the halt below is not delayed
            self.on_event("safety", {"latched": True, "reason": reason})
            for listener in list(self.safety_listeners):
                listener(reason)
        await self.halt()

    async def halt(self) -> None:
        """``stop()`` every motion device at once (no latch): the end of a cancelled or stopped motion."""
        stops = [d.stop() for ds in self.robots.values() for d in ds]
        results = await asyncio.gather(*(asyncio.wait_for(s, self.control_period_s * 5) for s in stops),
                                       return_exceptions=True)
        for r in results:
            if isinstance(r, BaseException):
                log.error("stop failed: %r", r)

    async def reset_safety(self) -> None:
        """Clear the latch; raises :class:`SafetyStop` while the safety inputs still forbid motion."""
        if self.safety_io is not None:
            state = await asyncio.wait_for(self.safety_io.read(), self.device_timeout_s)
            if not state.motion_allowed:
                raise SafetyStop("safety", "cannot reset: " + ("e-stop pressed" if state.estop
                                                                else "light curtain broken"))
        if self.latched_reason is not None:
            log.warning("safety stop reset (was: %s)", self.latched_reason)
            self.latched_reason = None
            self.on_event("safety", {"latched": False, "reason": None})

    # ------------------------------------------------------------ motion gate

    @property
    def moving_robots(self) -> list[str]:
        return sorted({m.robot for m in self._motions})

    @asynccontextmanager
    async def motion(self, robot: str) -> AsyncIterator[None]:
        """The gate every motion passes: refuses while latched, while one of the robot's devices is down (being
        reconnected: :class:`NotConnected`) or while another robot moves.

        A safety stop during the block interrupts it and raises :class:`SafetyStop`; a
        :class:`SafetyStop` from a device inside the block latches the stop for the whole cell.
        """
        if robot not in self.robots:
            raise ValueError(f"unknown robot {robot!r}; known: {sorted(self.robots)}")
        if self.latched_reason is not None:
            raise SafetyStop("supervisor", f"motion refused, safety stop latched: {self.latched_reason}")
        down = [d.name for d in self.robots[robot] if d.name in self.health and not self.health[d.name].up]
        if down:
            raise NotConnected(down[0], f"motion refused: {robot} robot's {down[0]} is down ("
                                        f"{self.health[down[0]].last_error or self.health[down[0]].state})")
        others = [m.robot for m in self._motions if m.robot != robot]
        if others:
            raise MotionInterlock("supervisor", f"{robot} robot may not move while {others[0]} robot is moving")
        entry = _Motion(robot, asyncio.current_task())
        self._motions.append(entry)
        try:
            yield
            if entry.tripped:
                await asyncio.sleep(0)  # take delivery of the pending cancel of a stop that came at the end
        except asyncio.CancelledError:
            if entry.tripped:
                entry.task.uncancel()
                raise SafetyStop("supervisor", f"motion halted: {self.latched_reason}") from None
            raise
        except SafetyStop as e:
            self._motions.remove(entry)
            await self.trip(str(e))
            raise
        finally:
            if entry in self._motions:
                self._motions.remove(entry)

    def snapshot(self) -> dict:
        """Devices, safety and motion now (JSON-able)."""
        return {
            "devices": [h.as_dict() for h in self.health.values()],
            "safety": {"latched": self.latched_reason is not None, "reason": self.latched_reason},
            "moving": self.moving_robots,
            "all_connected": self.all_connected,
        }


@dataclass
class DeviceHealth:
    """What the supervisor knows about one device (published on every change); ``next_retry_s``: when the next
    reconnect try is due (``time.monotonic()``, s), None when none is scheduled."""

    name: str
    connected: bool = False
    state: DeviceState = DeviceState.DISCONNECTED
    detail: dict = field(default_factory=dict)
    last_error: str | None = None
    reconnects: int = 0
    next_retry_s: float | None = None

    @property
    def up(self) -> bool:
        """Connected and not reporting a fault: a device a job can use."""
        return self.connected and self.state != DeviceState.FAULT

    def as_dict(self) -> dict:
        return {"name": self.name, "connected": self.connected, "state": self.state, "detail": self.detail,
                "last_error": self.last_error, "reconnects": self.reconnects}


def fault_reason(detail: Mapping) -> str:
    """The reason a device's own fault status gives (its ``error`` or ``fault`` detail)."""
    return str(detail.get("error") or detail.get("fault") or "the device reports a fault")


def backoff_delays(initial_s: float, max_s: float, jitter: float = 0.1,
                   rng: random.Random | None = None) -> Iterator[float]:
    """Exponential backoff: ``initial_s, 2 initial_s, ...`` capped at ``max_s``, each +- ``jitter`` fraction."""
    rng = rng or random.Random()
    delay = initial_s
    while True:
        yield min(delay, max_s) * (1.0 + rng.uniform(-jitter, jitter))
        delay = min(delay * 2.0, max_s)
