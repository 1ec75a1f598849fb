"""Metronor optical tracker: a framed 6-DoF pose stream over TCP or serial (settings in ``TrackerConfig.stream``).

The vendor protocol is not public, so the framing lives in one configurable adapter
(:class:`~tandemscan.drivers.pose_stream.PoseStreamAdapter`). :meth:`MetronorTracker.read_pose` waits for
frames that arrive after the call (never a stale one), averages ``samples_per_reading`` of them, and raises
:class:`TargetNotVisible` when the tracker reports the target missing or :class:`DeviceFault` for a frame it
cannot trust (checksum, NaN, non-unit rotation).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time

import numpy as np
import serial
from tandemscan.config.models import TrackerConfig
from tandemscan.drivers.errors import DeviceError, DeviceFault, DeviceTimeout, NotConnected, TargetNotVisible
from tandemscan.drivers.interfaces import DeviceStatus, TrackerReading
from tandemscan.drivers.pose_stream import PoseFrameError, PoseSample, PoseStreamAdapter
from tandemscan.pipeline.frames import make_transform, orthonormalize

log = logging.getLogger(__name__)


class MetronorTracker:
    """The :class:`~tandemscan.drivers.interfaces.Tracker` on a pose stream."""

    def __init__(self, config: TrackerConfig, name: str = "tracker"):
        self.name = name
        self._cfg = config
        self._stream = config.stream
        self._adapter = PoseStreamAdapter(config.stream)
        self._writer: asyncio.StreamWriter | None = None
        self._task: asyncio.Task | None = None
        self._serial: serial.Serial | None = None
        self._connected = False
        self._link_error: DeviceError | None = None
        self._frames: list[tuple[float, PoseSample | PoseFrameError]] = []  # (host time s, frame) since last read
        self._arrived = asyncio.Event()
        self.last_sample: PoseSample | None = None

    async def connect(self) -> None:
        await self.close()
        s = self._stream
        self._adapter = PoseStreamAdapter(s)
        self._link_error = None
        if s.transport == "tcp":
            try:
                reader, self._writer = await asyncio.wait_for(asyncio.open_connection(s.host, s.port),
                                                              self._cfg.timeout_s)
            except TimeoutError as e:
                raise DeviceTimeout(self.name, f"no connection to {s.host}:{s.port}") from e
            except OSError as e:
                raise NotConnected(self.name, f"cannot connect to {s.host}:{s.port}: {e}") from e
            self._task = asyncio.create_task(self._read_tcp(reader), name=f"{self.name}-stream")
        else:
            try:
                self._serial = serial.Serial(s.serial_device, s.baudrate, timeout=0)
            except (serial.SerialException, OSError, ValueError) as e:
                raise NotConnected(self.name, f"cannot open {s.serial_device}: {e}") from e
            asyncio.get_running_loop().add_reader(self._serial.fileno(), self._read_serial)
        self._connected = True
        log.info("%s: pose stream connected (%s)", self.name, s.transport)

    async def close(self) -> None:
        self._connected = False
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.close()
            with contextlib.suppress(OSError, TimeoutError):
                await asyncio.wait_for(writer.wait_closed(), 1.0)
        port, self._serial = self._serial, None
        if port is not None:
            with contextlib.suppress(OSError, ValueError):
                asyncio.get_running_loop().remove_reader(port.fileno())
            port.close()
        self._frames.clear()

    async def status(self) -> DeviceStatus:
        if not self._connected:
            return DeviceStatus(self.name, False, "disconnected")
        if self._link_error is not None:
            return DeviceStatus(self.name, True, "fault", {"error": str(self._link_error)})
        last = self.last_sample
        detail = {"frame": last.frame, "status": last.status} if last else {}
        return DeviceStatus(self.name, True, "idle", detail)

    async def read_pose(self, timeout_s: float | None = None) -> TrackerReading:
        """The mean of ``samples_per_reading`` fresh frames: ``T_C_T`` (mm), covariance, host time, frame number."""
        if not self._connected:
            raise NotConnected(self.name, "not connected")
        timeout = self._cfg.timeout_s if timeout_s is None else timeout_s
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        self._frames.clear()
        samples: list[tuple[float, PoseSample]] = []
        while len(samples) < self._cfg.samples_per_reading:
            while not self._frames:
                if self._link_error is not None:
                    raise self._link_error
                event = self._arrived
                try:
                    await asyncio.wait_for(event.wait(), max(deadline - loop.time(), 0.0))
                except TimeoutError as e:
                    raise DeviceTimeout(self.name, f"no pose frame within {timeout} s") from e
            host_t, frame = self._frames.pop(0)
            if isinstance(frame, PoseFrameError):
                raise DeviceFault(self.name, f"bad pose frame: {frame}")
            if not frame.visible:
                raise TargetNotVisible(self.name, f"target not visible (frame {frame.frame}, {frame.status})")
            samples.append((host_t, frame))
        return self._average(samples)

    def _average(self, samples: list[tuple[float, PoseSample]]) -> TrackerReading:
        n = len(samples)
        Ts = np.array([s.T_C_T for _, s in samples])
        R = orthonormalize(make_transform(Ts[:, :3, :3].mean(axis=0), Ts[:, :3, 3].mean(axis=0)))
        cov = np.mean([s.covariance for _, s in samples], axis=0) / n
        return TrackerReading(T_C_T=R, covariance=cov, timestamp_s=float(np.mean([t for t, _ in samples])),
                              frame_number=samples[-1][1].frame)

    # ------------------------------------------------------------------ receive paths

    def _accept(self, data: bytes) -> None:
        now = time.time()
        for item in self._adapter.feed(data):
            if isinstance(item, PoseSample):
                self.last_sample = item
            self._frames.append((now, item))
        del self._frames[:-1000]  # bounded when nobody reads
        self._arrived.set()
        self._arrived = asyncio.Event()

    def _lost(self, error: DeviceError) -> None:
        self._link_error = error
        self._arrived.set()
        self._arrived = asyncio.Event()

    async def _read_tcp(self, reader: asyncio.StreamReader) -> None:
        try:
            while True:
                data = await reader.read(65536)
                if not data:
                    self._lost(NotConnected(self.name, "pose stream closed by the tracker"))
                    return
                self._accept(data)
        except (ConnectionError, OSError) as e:
            self._lost(NotConnected(self.name, f"pose stream lost: {e}"))

    def _read_serial(self) -> None:
        port = self._serial
        if port is None:
            return
        try:
            data = port.read(port.in_waiting or 1)
        except (serial.SerialException, OSError) as e:
            asyncio.get_running_loop().remove_reader(port.fileno())
            self._lost(NotConnected(self.name, f"serial read failed: {e}"))
            return
        self._accept(data)
