"""The ACME tracker's driver: one JSON request a reading over TCP (the protocol of :mod:`acme_tracker.emulator`).

The tracker answers ``{"cmd": "pose"}`` with the target's pose in metres and a unit quaternion (w, x, y, z) and
its 1-sigma in mm and degrees, or ``{"visible": false, "reason": ...}``; the driver converts once, here, to the
cell's mm, rad and 4x4 ``T_C_T``.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import time

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from tandemscan.drivers.errors import DeviceFault, DeviceTimeout, NotConnected, TargetNotVisible
from tandemscan.drivers.interfaces import DeviceState, DeviceStatus, TrackerReading
from tandemscan.pipeline.geometry import frames as F


class AcmeSettings(BaseModel):
    """The ``[tracker.acme]`` table: where the tracker listens and how long a reply may take."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    host: str = "127.0.0.1"
    port: int = Field(9876, ge=0, le=65535)
    reply_timeout_s: float = Field(2.0, gt=0)


class AcmeTracker:
    """The :class:`~tandemscan.drivers.interfaces.Tracker` of an ACME tracker."""

    Settings = AcmeSettings

    def __init__(self, section, name: str = "tracker"):
        self.name = name
        self.settings: AcmeSettings = section.settings
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._frames = 0

    async def connect(self) -> None:
        await self.close()
        s = self.settings
        try:
            async with asyncio.timeout(s.reply_timeout_s):
                self._reader, self._writer = await asyncio.open_connection(s.host, s.port)
        except TimeoutError as e:
            raise DeviceTimeout(self.name, f"no connection to {s.host}:{s.port}") from e
        except OSError as e:
            raise NotConnected(self.name, f"{s.host}:{s.port}: {e.strerror}") from e

    async def close(self) -> None:
        writer, self._reader, self._writer = self._writer, None, None
        if writer is not None:
            writer.close()
            with contextlib.suppress(OSError):
                await writer.wait_closed()

    async def status(self) -> DeviceStatus:
        connected = self._writer is not None
        return DeviceStatus(self.name, connected, DeviceState.IDLE if connected else DeviceState.DISCONNECTED,
                            {"frames": self._frames})

    async def read_pose(self, timeout_s: float | None = None) -> TrackerReading:
        if self._writer is None:
            raise NotConnected(self.name, "not connected")
        self._writer.write(b'{"cmd": "pose"}\n')
        try:
            async with asyncio.timeout(timeout_s or self.settings.reply_timeout_s):
                line = await self._reader.readline()
        except TimeoutError as e:
            raise DeviceTimeout(self.name, "no reply within the timeout") from e
        if not line:
            await self.close()
            raise NotConnected(self.name, "the tracker closed the connection")
        try:
            reply = json.loads(line)
        except json.JSONDecodeError as e:
            raise DeviceFault(self.name, f"unreadable reply {line[:40]!r}") from e
        if not reply.get("visible"):
            raise TargetNotVisible(self.name, reply.get("reason", "target not visible"))
        w, x, y, z = reply["quaternion_wxyz"]
        T_C_T = F.from_quaternion(np.asarray(reply["position_m"], float) * 1000.0, [x, y, z, w])
        sigma_rad = math.radians(reply["sigma_deg"])
        covariance = np.diag([reply["sigma_mm"] ** 2] * 3 + [sigma_rad**2] * 3)
        self._frames += 1
        return TrackerReading(T_C_T, covariance, time.time(), self._frames)
