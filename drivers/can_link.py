"""A python-can bus with asyncio receive and DBC encoding (cantools): the transport under the chassis driver
and its emulator. A frame whose length does not match the database is reported, never silently decoded."""

from __future__ import annotations

import asyncio
import logging
from importlib import resources
from pathlib import Path

import can
import cantools
from cantools.database import Database
from cantools.database.errors import DecodeError, EncodeError

log = logging.getLogger(__name__)

DEFAULT_DBC = "agilex_scout_v2.dbc"


class CanFrameError(ValueError):
    """A received frame does not match the database (wrong DLC, undecodable), or a value cannot be encoded."""


def load_dbc(path: Path | None = None) -> Database:
    """The CAN database at ``path``, or the shipped AgileX-Scout-style v2 database."""
    if path is None:
        path = Path(str(resources.files("tandemscan.config").joinpath(DEFAULT_DBC)))
    return cantools.database.load_file(str(path))


class CanLink:
    """One bus, one receive queue. ``recv()`` yields ``(message name, signals, raw frame)`` for known IDs."""

    def __init__(self, interface: str, channel: str, bitrate: int, db: Database):
        self.interface, self.channel, self.bitrate, self.db = interface, channel, bitrate, db
        self._bus: can.BusABC | None = None
        self._notifier: can.Notifier | None = None
        self._reader: can.AsyncBufferedReader | None = None

    @property
    def is_open(self) -> bool:
        return self._bus is not None

    def open(self) -> None:
        """Open the bus and start receiving into an asyncio queue (call from the running loop)."""
        self._bus = can.Bus(interface=self.interface, channel=self.channel, bitrate=self.bitrate)
        self._reader = can.AsyncBufferedReader()
        self._notifier = can.Notifier(self._bus, [self._reader], timeout=0.05, loop=asyncio.get_running_loop())

    async def close(self) -> None:
        """Stop receiving and shut the bus down; safe to call twice."""
        notifier, bus = self._notifier, self._bus
        self._notifier = self._bus = self._reader = None
        if notifier is not None:
            await asyncio.to_thread(notifier.stop, 0.5)
        if bus is not None:
            bus.shutdown()

    def send(self, name: str, **signals: float) -> None:
        """Encode message ``name`` from physical signal values and put it on the bus."""
        if self._bus is None:
            raise can.CanOperationError("bus is closed")
        spec = self.db.get_message_by_name(name)
        try:
            data = spec.encode(signals, strict=True)
        except EncodeError as e:
            raise CanFrameError(f"{name}: {e}") from e
        self._bus.send(can.Message(arbitration_id=spec.frame_id, data=data, is_extended_id=spec.is_extended_frame))

    def send_raw(self, frame_id: int, data: bytes) -> None:
        """Put raw bytes on the bus (fault injection: frames that do not match the database)."""
        if self._bus is None:
            raise can.CanOperationError("bus is closed")
        self._bus.send(can.Message(arbitration_id=frame_id, data=data, is_extended_id=False))

    async def recv(self) -> tuple[str, dict[str, float], can.Message]:
        """The next frame with an ID in the database; :class:`CanFrameError` for one that does not decode."""
        while True:
            if self._reader is None:
                raise can.CanOperationError("bus is closed")
            msg = await self._reader.get_message()
            if msg.is_error_frame or msg.is_remote_frame:
                continue
            try:
                spec = self.db.get_message_by_frame_id(msg.arbitration_id)
            except KeyError:
                continue
            if msg.dlc != spec.length:
                raise CanFrameError(f"{spec.name} (0x{spec.frame_id:03X}) with DLC {msg.dlc}, expected {spec.length}")
            try:
                return spec.name, spec.decode(bytes(msg.data), decode_choices=False), msg
            except DecodeError as e:
                raise CanFrameError(f"{spec.name}: {e}") from e
