"""Cell safety I/O over Modbus TCP (pymodbus): e-stop and light-curtain inputs, target light and beacon outputs.

Outputs are coils (I/O modules) or holding registers (PATLITE-style stack lights: ``*_on_value`` for on, 0 for
off), as configured per output.

The safety functions themselves stay hard-wired; this driver reports their state. Inputs are polled every
``SafetyConfig.poll_period_s`` in a background task; listeners hear every change at once. A lost or
misbehaving link counts as a safety stop: :meth:`ModbusSafetyIO.read` raises :class:`SafetyStop` until the
link is back (``connect()`` again). So does a silent module: a poll left unanswered for more than
``SafetyConfig.silent_after_periods`` (2) poll periods, and one more in which the event loop may take a reply that
came while it was held up, makes :meth:`ModbusSafetyIO.read` raise :class:`SafetyStop`, long before the request's
own timeout.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable

from pymodbus.client import AsyncModbusTcpClient
from pymodbus.exceptions import ModbusException
from tandemscan.config.models import SafetyConfig
from tandemscan.drivers.errors import DeviceError, DeviceFault, DeviceTimeout, NotConnected, SafetyStop
from tandemscan.drivers.interfaces import DeviceState, DeviceStatus, SafetyListener, SafetyState
from tandemscan.drivers.tasks import cancel_and_wait

log = logging.getLogger(__name__)


class ModbusSafetyIO:
    """The :class:`~tandemscan.drivers.interfaces.SafetyIO` on a Modbus TCP I/O module (``SafetyConfig.modbus``)."""

    def __init__(self, config: SafetyConfig, name: str = "safety"):
        self.name = name
        self._cfg = config
        self._mb = config.modbus
        self._client: AsyncModbusTcpClient | None = None
        self._task: asyncio.Task | None = None
        self._lock = asyncio.Lock()
        self._state: SafetyState | None = None
        self._light = False
        self._link_error: DeviceError | None = None
        self._poll_sent_at: float | None = None  # loop time (s) of the poll request awaiting its reply
        self._poll_answered = asyncio.Event()  # set when that poll's reply (or the link's loss) is taken
        self._listeners: list[SafetyListener] = []

    def add_listener(self, listener: SafetyListener) -> None:
        """Call ``listener(state)`` whenever the polled state changes (a lost link reads as e-stop): the
        supervisor's safety loop is woken by it (:class:`~tandemscan.drivers.interfaces.PushesSafetyChanges`)."""
        self._listeners.append(listener)

    async def connect(self) -> None:
        await self.close()
        client = AsyncModbusTcpClient(self._mb.host, port=self._mb.port, timeout=self._mb.timeout_s, retries=0,
                                      reconnect_delay=0, trace_connect=self._on_connection_change)
        try:
            async with asyncio.timeout(self._mb.timeout_s):
                ok = await client.connect()
        except TimeoutError:
            ok = False
        if not ok:
            client.close()
            raise NotConnected(self.name, f"cannot connect to Modbus {self._mb.host}:{self._mb.port}")
        self._client, self._link_error = client, None
        try:
            await self._poll_once()
            self._light = await self._read_output("target light", self._mb.target_light_coil,
                                                  self._mb.target_light_output, self._mb.target_light_on_value)
        except DeviceError:
            await self.close()
            raise
        self._task = asyncio.create_task(self._poll_loop(), name=f"{self.name}-poll")

    async def close(self) -> None:
        task, self._task = self._task, None
        await cancel_and_wait(task)
        client, self._client = self._client, None
        if client is not None:
            client.close()
        self._state = None
        self._poll_sent_at = None

    async def status(self) -> DeviceStatus:
        if self._client is None:
            return DeviceStatus(self.name, False, DeviceState.DISCONNECTED)
        if self._link_error is not None:
            return DeviceStatus(self.name, True, DeviceState.FAULT, {"error": str(self._link_error)})
        st = self._state
        state = DeviceState.IDLE if st is not None and st.motion_allowed else DeviceState.STOPPED
        return DeviceStatus(self.name, True, state, {"state": st})

    async def read(self) -> SafetyState:
        """The latest polled state; :class:`SafetyStop` while the link is lost."""
        if self._client is None:
            raise NotConnected(self.name, "not connected")
        if self._link_error is not None:
            raise SafetyStop(self.name, f"safety I/O link lost ({self._link_error.reason})")
        if self._silent_s() is not None:
            await self._take_late_reply()
            silent_s = self._silent_s()
            if silent_s is not None:
                raise SafetyStop(self.name, f"safety I/O silent: no reply to a poll for {1000.0 * silent_s:.0f} ms")
        assert self._state is not None
        return self._state

    async def _take_late_reply(self) -> None:
        """Give the event loop one poll period to take the reply of the poll in flight: a module answers while
        this loop is held up by other work, and its reply then waits in the socket for a few loop turns (the
        client's data callback, its transaction, the poll task). A silent module is reported one period later."""
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(self._cfg.poll_period_s):
                await self._poll_answered.wait()

    def _silent_s(self) -> float | None:
        """How long the poll in flight has waited for its reply (s), once that is over ``silent_after_periods``
        poll periods; None otherwise."""
        sent = self._poll_sent_at
        if sent is None:
            return None
        waited_s = asyncio.get_running_loop().time() - sent
        return waited_s if waited_s > self._cfg.silent_after_periods * self._cfg.poll_period_s else None

    async def set_target_light(self, on: bool) -> None:
        mb = self._mb
        await self._write_output("target light", mb.target_light_coil, mb.target_light_output,
                                 mb.target_light_on_value, on)
        self._light = on

    async def set_beacon(self, on: bool) -> None:
        mb = self._mb
        await self._write_output("beacon", mb.beacon_coil, mb.beacon_output, mb.beacon_on_value, on)

    # ------------------------------------------------------------------ Modbus side

    async def _write_output(self, what: str, address: int, kind: str, on_value: int, on: bool) -> None:
        """Switch one output: a coil, or a holding register written ``on_value`` / 0."""
        client = self._client
        if client is None:
            raise NotConnected(self.name, "not connected")
        if kind == "coil":
            await self._request(f"write {what}", client.write_coil, address, bool(on))
        else:
            await self._request(f"write {what}", client.write_register, address, on_value if on else 0)

    async def _read_output(self, what: str, address: int, kind: str, on_value: int) -> bool:
        """Whether one output is on now (a set coil, or a register holding ``on_value``)."""
        client = self._client
        if client is None:
            raise NotConnected(self.name, "not connected")
        if kind == "coil":
            return bool((await self._request(f"read {what}", client.read_coils, address)).bits[0])
        rr = await self._request(f"read {what}", client.read_holding_registers, address, count=1)
        return int(rr.registers[0]) == on_value

    async def _request(self, what: str, call: Callable, address: int, *args: object, **kw: object):
        """One Modbus request with the configured timeout; an exception response is a :class:`DeviceFault`."""
        async with self._lock:
            if self._client is None or not self._client.connected:
                raise NotConnected(self.name, f"{what}: connection to the I/O module lost")
            try:
                async with asyncio.timeout(self._mb.timeout_s):  # not wait_for: it can swallow a cancel in 3.11
                    rr = await call(address, *args, device_id=self._mb.device_id, **kw)
            except TimeoutError as e:
                raise DeviceTimeout(self.name, f"{what}: no reply within {self._mb.timeout_s} s") from e
            except (ModbusException, ConnectionError, OSError) as e:
                raise NotConnected(self.name, f"{what}: {e}") from e
        if rr.isError():
            raise DeviceFault(self.name, f"{what}: exception response {getattr(rr, 'exception_code', rr)}")
        return rr

    async def _poll_once(self) -> SafetyState:
        client = self._client
        if client is None:
            raise NotConnected(self.name, "not connected")
        first = min(self._mb.estop_input, self._mb.light_curtain_input)
        count = max(self._mb.estop_input, self._mb.light_curtain_input) - first + 1
        self._poll_sent_at, self._poll_answered = asyncio.get_running_loop().time(), asyncio.Event()
        try:
            rr = await self._request("read inputs", client.read_discrete_inputs, first, count=count)
        finally:
            self._poll_answered.set()
        self._poll_sent_at = None
        bits = list(rr.bits)
        if len(bits) < count:
            raise DeviceFault(self.name, f"read inputs: {len(bits)} bits for {count} requested")
        estop = bool(bits[self._mb.estop_input - first]) == self._mb.estop_active_high
        curtain = bool(bits[self._mb.light_curtain_input - first]) == self._mb.light_curtain_active_high
        state = SafetyState(estop=estop, light_curtain_broken=curtain, target_light_on=self._light)
        self._publish(state)
        return state

    def _publish(self, state: SafetyState) -> None:
        if state != self._state:
            self._state = state
            if not state.motion_allowed:
                log.warning("%s: %s", self.name, state)
            for listener in self._listeners:
                listener(state)

    def _lost(self, error: DeviceError) -> None:
        """The link is gone: remember why and tell listeners to stop motion."""
        if self._link_error is None:
            self._link_error = error
            log.error("%s: link lost, counted as a safety stop: %s", self.name, error)
            self._publish(SafetyState(estop=True, light_curtain_broken=True, target_light_on=self._light))

    def _on_connection_change(self, connected: bool) -> None:
        """pymodbus reports a dropped socket here at once, while a request in flight would wait for its timeout."""
        if not connected and self._client is not None:
            self._lost(NotConnected(self.name, "connection to the I/O module closed"))
            if self._task is not None:
                self._task.cancel()

    async def _poll_loop(self) -> None:
        loop = asyncio.get_running_loop()
        next_t = loop.time()
        while True:
            try:
                await self._poll_once()
            except DeviceError as e:
                self._lost(e)
                return
            next_t += self._cfg.poll_period_s
            await asyncio.sleep(max(0.0, next_t - loop.time()))
