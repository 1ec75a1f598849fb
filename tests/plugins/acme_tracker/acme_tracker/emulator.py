"""The ACME tracker's emulator: answers each ``{"cmd": "pose"}`` line with the simulated world's reading of the
target, in the vendor's units (metres, a w-first quaternion, sigma in mm and degrees)."""

from __future__ import annotations

import asyncio
import json
import math

import numpy as np
from tandemscan.drivers.errors import TargetNotVisible
from tandemscan.pipeline.geometry import frames as F
from tandemscan.sim_drivers.emulators.tcp_server import TcpService


class AcmeEmulator:
    """A TCP server on ``settings.host:settings.port`` reading ``world.measure_target()`` per request."""

    def __init__(self, settings, world):
        self.settings, self.world = settings, world
        self.requests = 0
        self._tcp = TcpService(self._serve, settings.host, settings.port)

    async def start(self) -> None:
        await self._tcp.start()

    async def stop(self) -> None:
        await self._tcp.stop()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        while line := await reader.readline():
            self.requests += 1
            writer.write((json.dumps(self._reply(json.loads(line))) + "\n").encode())
            await writer.drain()

    def _reply(self, request: dict) -> dict:
        if request.get("cmd") != "pose":
            return {"visible": False, "reason": f"unknown command {request.get('cmd')!r}"}
        try:
            T_C_T, covariance = self.world.measure_target()
        except TargetNotVisible as e:
            return {"visible": False, "reason": e.reason}
        position_mm, (x, y, z, w) = F.to_quaternion(T_C_T)
        return {"visible": True, "position_m": (np.asarray(position_mm) / 1000.0).tolist(),
                "quaternion_wxyz": [float(w), float(x), float(y), float(z)],
                "sigma_mm": float(math.sqrt(covariance[0, 0])), "sigma_deg": math.degrees(math.sqrt(covariance[3, 3]))}


async def start(section, world) -> AcmeEmulator:
    """The running emulator of ``section.settings`` on ``world`` (the hardware-in-the-loop cell starts it)."""
    emulator = AcmeEmulator(section.settings, world)
    await emulator.start()
    return emulator
