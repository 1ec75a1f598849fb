"""Safety I/O emulator: a Modbus TCP I/O module served by pymodbus' own server on 127.0.0.1.

Discrete inputs carry the e-stop and light-curtain contacts, coils or holding registers (a stack light) the
target light and beacon, at the addresses of :class:`~tandemscan.config.models.SafetyModbusConfig`. Faults:
exception replies, silence (no reply), and a restart that drops every connection. The server runs on its own
event loop in its own thread, as a module is hardware of its own.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import TypeVar

from pymodbus.constants import ExcCodes
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice
from tandemscan.config.models import SafetyModbusConfig

log = logging.getLogger(__name__)

_FC_COILS, _FC_DISCRETE_INPUTS, _FC_HOLDING_REGISTERS = 1, 2, 3
_BLOCK = 32
T = TypeVar("T")


@dataclass
class ModbusFaults:
    """Fault injection; flags may change while the emulator runs."""

    exception_replies: bool = False  # every reply becomes a device-failure exception response
    silent: bool = False  # requests are read, never answered


class SafetyIoEmulator:
    """``start()`` returns the port; ``set_input`` presses buttons, ``coil`` reads what the driver wrote.

    The module is hardware of its own: its server runs on an event loop in a thread of its own, so it answers a
    poll while the event loop of the driver (the daemon's, in the hardware-in-the-loop cell) is held up by other
    work, as a real module does. Every method may be awaited from any event loop; the fault flags are plain
    attributes."""

    def __init__(self, cfg: SafetyModbusConfig, host: str = "127.0.0.1", port: int = 0):
        self.cfg = cfg
        self.host, self.port = host, port
        self.faults = ModbusFaults()
        self._server: ModbusTcpServer | None = None
        self._inputs: dict[int, bool] = {}
        self._coils: dict[int, bool] = {}
        self._registers: dict[int, int] = {}
        self._loop: asyncio.AbstractEventLoop | None = None  # the module's own, in self._thread
        self._thread: threading.Thread | None = None

    async def _on_module(self, call: Callable[[], Awaitable[T]]) -> T:
        """Run ``call()`` on the module's event loop (its thread started if need be) and await its result."""
        if self._loop is None:
            ready = threading.Event()
            self._thread = threading.Thread(target=self._run_loop, args=(ready,), name="modbus-module", daemon=True)
            self._thread.start()
            ready.wait()
        assert self._loop is not None
        return await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(call(), self._loop))

    def _run_loop(self, ready: threading.Event) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        ready.set()
        try:
            loop.run_forever()
        finally:
            loop.close()

    async def start(self) -> int:
        """Listen (again, on the same port after a restart); returns the port."""
        return await self._on_module(self._start)

    async def _start(self) -> int:
        bits = [SimData(0, count=_BLOCK, values=False, datatype=DataType.BITS)]
        regs = [SimData(0, count=_BLOCK, values=0, datatype=DataType.REGISTERS)]
        device = SimDevice(self.cfg.device_id, simdata=(list(bits), list(bits), list(regs), list(regs)))
        self._server = ModbusTcpServer(device, address=(self.host, self.port), trace_pdu=self._trace_pdu,
                                       trace_packet=self._trace_packet)
        await self._server.serve_forever(background=True)
        self.port = self._server.transport.sockets[0].getsockname()[1]
        for address, value in self._inputs.items():
            await self._set_values(_FC_DISCRETE_INPUTS, address, value)
        for address, value in self._coils.items():
            await self._set_values(_FC_COILS, address, value)
        for address, value in self._registers.items():
            await self._set_values(_FC_HOLDING_REGISTERS, address, value)
        return self.port

    async def stop(self) -> None:
        """Shut the server down and end the module's thread."""
        if self._loop is None:
            return
        await self._on_module(self._stop)
        loop, thread = self._loop, self._thread
        self._loop = self._thread = None
        loop.call_soon_threadsafe(loop.stop)
        assert thread is not None
        await asyncio.to_thread(thread.join)

    async def _stop(self) -> None:
        if self._server is not None:
            outputs = ((self.cfg.target_light_coil, self.cfg.target_light_output),
                       (self.cfg.beacon_coil, self.cfg.beacon_output))
            for address, kind in outputs:
                if kind == "coil":
                    self._coils[address] = bool((await self._get_values(_FC_COILS, address))[0])
                else:
                    self._registers[address] = int((await self._get_values(_FC_HOLDING_REGISTERS, address))[0])
            await self._server.shutdown()
            self._server = None

    async def restart(self) -> None:
        """Drop every connection and listen again (a link loss the driver must recover from)."""
        await self._on_module(self._stop)
        await self._on_module(self._start)

    async def set_input(self, address: int, value: bool) -> None:
        """Set a discrete input (wire level: true = contact closed)."""
        self._inputs[address] = value
        if self._loop is not None:
            await self._on_module(lambda: self._set_values(_FC_DISCRETE_INPUTS, address, value))

    async def press_estop(self, pressed: bool = True) -> None:
        await self.set_input(self.cfg.estop_input, pressed == self.cfg.estop_active_high)

    async def break_light_curtain(self, broken: bool = True) -> None:
        await self.set_input(self.cfg.light_curtain_input, broken == self.cfg.light_curtain_active_high)

    async def coil(self, address: int) -> bool:
        return bool((await self._on_module(lambda: self._get_values(_FC_COILS, address)))[0])

    async def register(self, address: int) -> int:
        """A holding register's value (a stack-light tier)."""
        return int((await self._on_module(lambda: self._get_values(_FC_HOLDING_REGISTERS, address)))[0])

    async def _set_values(self, function_code: int, address: int, value: bool | int) -> None:
        if self._server is not None:
            await self._server.async_setValues(self.cfg.device_id, function_code, address, [value])

    async def _get_values(self, function_code: int, address: int) -> list:
        assert self._server is not None
        return await self._server.async_getValues(self.cfg.device_id, function_code, address, 1)

    def _trace_pdu(self, sending: bool, pdu: ModbusPDU) -> ModbusPDU:
        if sending and self.faults.exception_replies:
            return ExceptionResponse(pdu.function_code & 0x7F, ExcCodes.DEVICE_FAILURE, pdu.dev_id,
                                     pdu.transaction_id)
        return pdu

    def _trace_packet(self, sending: bool, packet: bytes) -> bytes:
        return b"" if sending and self.faults.silent else packet
