"""Safety I/O emulator: a Modbus TCP I/O module served by pymodbus' own server on 127.0.0.1.

Discrete inputs carry the e-stop and light-curtain contacts, coils or holding registers (a stack light) the
target light and beacon, at the addresses of :class:`~tandemscan.config.models.SafetyModbusConfig`. Faults:
exception replies, silence (no reply), and a restart that drops every connection.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from pymodbus.constants import ExcCodes
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice
from tandemscan.config.models import SafetyModbusConfig

log = logging.getLogger(__name__)

_FC_COILS, _FC_DISCRETE_INPUTS, _FC_HOLDING_REGISTERS = 1, 2, 3
_BLOCK = 32


@dataclass
class ModbusFaults:
    """Fault injection; flags may change while the emulator runs."""

    exception_replies: bool = False  # every reply becomes a device-failure exception response
    silent: bool = False  # requests are read, never answered


class SafetyIoEmulator:
    """``start()`` returns the port; ``set_input`` presses buttons, ``coil`` reads what the driver wrote."""

    def __init__(self, cfg: SafetyModbusConfig, host: str = "127.0.0.1", port: int = 0):
        self.cfg = cfg
        self.host, self.port = host, port
        self.faults = ModbusFaults()
        self._server: ModbusTcpServer | None = None
        self._inputs: dict[int, bool] = {}
        self._coils: dict[int, bool] = {}
        self._registers: dict[int, int] = {}

    async def start(self) -> int:
        """Listen (again, on the same port after a restart); returns the port."""
        bits = [SimData(0, count=_BLOCK, values=False, datatype=DataType.BITS)]
        regs = [SimData(0, count=_BLOCK, values=0, datatype=DataType.REGISTERS)]
        device = SimDevice(self.cfg.device_id, simdata=(list(bits), list(bits), list(regs), list(regs)))
        self._server = ModbusTcpServer(device, address=(self.host, self.port), trace_pdu=self._trace_pdu,
                                       trace_packet=self._trace_packet)
        await self._server.serve_forever(background=True)
        self.port = self._server.transport.sockets[0].getsockname()[1]
        for address, value in self._inputs.items():
            await self.set_input(address, value)
        for address, value in self._coils.items():
            await self._server.async_setValues(self.cfg.device_id, _FC_COILS, address, [value])
        for address, value in self._registers.items():
            await self._server.async_setValues(self.cfg.device_id, _FC_HOLDING_REGISTERS, address, [value])
        return self.port

    async def stop(self) -> None:
        if self._server is not None:
            outputs = ((self.cfg.target_light_coil, self.cfg.target_light_output),
                       (self.cfg.beacon_coil, self.cfg.beacon_output))
            for address, kind in outputs:
                if kind == "coil":
                    self._coils[address] = await self.coil(address)
                else:
                    self._registers[address] = await self.register(address)
            await self._server.shutdown()
            self._server = None

    async def restart(self) -> None:
        """Drop every connection and listen again (a link loss the driver must recover from)."""
        await self.stop()
        await self.start()

    async def set_input(self, address: int, value: bool) -> None:
        """Set a discrete input (wire level: true = contact closed)."""
        self._inputs[address] = value
        if self._server is not None:
            await self._server.async_setValues(self.cfg.device_id, _FC_DISCRETE_INPUTS, address, [value])

    async def press_estop(self, pressed: bool = True) -> None:
        await self.set_input(self.cfg.estop_input, pressed == self.cfg.estop_active_high)

    async def break_light_curtain(self, broken: bool = True) -> None:
        await self.set_input(self.cfg.light_curtain_input, broken == self.cfg.light_curtain_active_high)

    async def coil(self, address: int) -> bool:
        assert self._server is not None
        return bool((await self._server.async_getValues(self.cfg.device_id, _FC_COILS, address, 1))[0])

    async def register(self, address: int) -> int:
        """A holding register's value (a stack-light tier)."""
        assert self._server is not None
        return int((await self._server.async_getValues(self.cfg.device_id, _FC_HOLDING_REGISTERS, address, 1))[0])

    def _trace_pdu(self, sending: bool, pdu: ModbusPDU) -> ModbusPDU:
        if sending and self.faults.exception_replies:
            return ExceptionResponse(pdu.function_code & 0x7F, ExcCodes.DEVICE_FAILURE, pdu.dev_id,
                                     pdu.transaction_id)
        return pdu

    def _trace_packet(self, sending: bool, packet: bytes) -> bytes:
        return b"" if sending and self.faults.silent else packet
