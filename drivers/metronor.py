"""Metronor optical tracker: a framed 6-DoF pose stream over TCP, serial or UDP (``TrackerConfig.stream``).

The vendor protocol is not public, so framing and record layout live in one configurable adapter
(:class:`~tandemscan.drivers.pose_stream.PoseStreamAdapter`). A tracker that must be asked gets its
``start_command`` once after connecting and its ``poll_command`` before every reading. Every frame is
timestamped on its own: frames that arrive together in one read (a stalled network delivers several at
once) are dated back by their device-time differences to the newest. :meth:`MetronorTracker.read_pose`
returns the first frame dated after the call (never a stale one), and raises :class:`TargetNotVisible` when
the tracker reports the target missing or :class:`DeviceFault` for a frame it cannot trust (checksum, NaN,
non-unit rotation).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time

import serial
from tandemscan.config.models import TrackerConfig
from tandemscan.drivers.errors import DeviceError, DeviceFault, DeviceTimeout, NotConnected, TargetNotVisible
from tandemscan.drivers.interfaces import DeviceState, DeviceStatus, TrackerReading
from tandemscan.drivers.pose_stream import PoseFrameError, PoseSample, PoseStreamAdapter
from tandemscan.drivers.tasks import cancel_and_wait

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
        self._udp: asyncio.DatagramTransport | None = None
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
                async with asyncio.timeout(self._cfg.timeout_s):
                    reader, self._writer = await asyncio.open_connection(s.host, s.port)
            except TimeoutError as e:
                raise DeviceTimeout(self.name, f"no connection to {s.host}:{s.port}") from e
            except OSError as e:
                raise NotConnected(self.name, f"cannot connect to {s.host}:{s.port}: {e}") from e
            self._task = asyncio.create_task(self._read_tcp(reader), name=f"{self.name}-stream")
        elif s.transport == "udp":
            try:
                self._udp, _ = await asyncio.get_running_loop().create_datagram_endpoint(
                    lambda: _DatagramReceiver(self), local_addr=(s.host, s.port))
            except OSError as e:
                raise NotConnected(self.name, f"cannot listen on UDP {s.host}:{s.port}: {e}") from e
        else:
            try:
                self._serial = serial.Serial(s.serial_device, s.baudrate, timeout=0)
            except (serial.SerialException, OSError, ValueError) as e:
                raise NotConnected(self.name, f"cannot open {s.serial_device}: {e}") from e
            asyncio.get_running_loop().add_reader(self._serial.fileno(), self._read_serial)
        self._connected = True
        if s.start_command:
            self._send(s.start_command)
        log.info("%s: pose stream connected (%s)", self.name, s.transport)

    async def close(self) -> None:
        self._connected = False
        task, self._task = self._task, None
        await cancel_and_wait(task)
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.close()
            with contextlib.suppress(OSError, TimeoutError):
                await asyncio.wait_for(writer.wait_closed(), 1.0)
        udp, self._udp = self._udp, None
        if udp is not None:
            udp.close()
        port, self._serial = self._serial, None
        if port is not None:
            with contextlib.suppress(OSError, ValueError):
                asyncio.get_running_loop().remove_reader(port.fileno())
            port.close()
        self._frames.clear()

    async def status(self) -> DeviceStatus:
        if not self._connected:
            return DeviceStatus(self.name, False, DeviceState.DISCONNECTED)
        if self._link_error is not None:
            return DeviceStatus(self.name, True, DeviceState.FAULT, {"error": str(self._link_error)})
        last = self.last_sample
        detail = {"frame": last.frame, "status": last.status} if last else {}
        return DeviceStatus(self.name, True, DeviceState.IDLE, detail)

    async def read_pose(self, timeout_s: float | None = None) -> TrackerReading:
        """The first frame that arrives after the call: ``T_C_T`` (mm), covariance, host time, frame number.

        One frame per call, as the twin: averaging over ``samples_per_reading`` is the job runner's.
        """
        if not self._connected:
            raise NotConnected(self.name, "not connected")
        timeout = self._cfg.timeout_s if timeout_s is None else timeout_s
        deadline = asyncio.get_running_loop().time() + timeout
        self._frames.clear()
        called_at = time.time()
        if self._stream.poll_command:
            self._send(self._stream.poll_command)
        while not (fresh := [f for f in self._frames if f[0] >= called_at]):
            if self._link_error is not None:
                raise self._link_error
            try:
                async with asyncio.timeout_at(deadline):
                    await self._arrived.wait()
            except TimeoutError as e:
                raise DeviceTimeout(self.name, f"no pose frame within {timeout} s") from e
        host_t, frame = fresh[0]
        if isinstance(frame, PoseFrameError):
            raise DeviceFault(self.name, f"bad pose frame: {frame}")
        if not frame.visible:
            raise TargetNotVisible(self.name, f"target not visible (frame {frame.frame}, {frame.status})")
        return TrackerReading(T_C_T=frame.T_C_T, covariance=frame.covariance, timestamp_s=host_t,
                              frame_number=frame.frame)

    # ------------------------------------------------------------------ receive paths

    def _send(self, command: str) -> None:
        """Write a command to the tracker (start or poll); a failing link shows up on the receive side."""
        data = command.encode("ascii")
        if self._writer is not None:
            self._writer.write(data)
        elif self._serial is not None:
            with contextlib.suppress(serial.SerialException, OSError):
                self._serial.write(data)

    def _accept(self, data: bytes, datagram: bool = False) -> None:
        """Take the frames in ``data``, each with its own host time (s): the newest frame with a device time
        gets the arrival time, earlier ones are dated back by their device-time difference to it."""
        now = time.time()
        items = self._adapter.feed_datagram(data) if datagram else self._adapter.feed(data)
        times = [i.device_time_s for i in items if isinstance(i, PoseSample) and math.isfinite(i.device_time_s)]
        newest = max(times, default=math.nan)
        for item in items:
            host_t = now
            if isinstance(item, PoseSample):
                self.last_sample = item
                if math.isfinite(item.device_time_s) and math.isfinite(newest):
                    host_t = now - (newest - item.device_time_s)
            self._frames.append((host_t, item))
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


class _DatagramReceiver(asyncio.DatagramProtocol):
    """Hands every datagram to the tracker as one whole batch of frames."""

    def __init__(self, tracker: MetronorTracker):
        self._tracker = tracker

    def datagram_received(self, data: bytes, addr: tuple) -> None:
        self._tracker._accept(data, datagram=True)

    def error_received(self, exc: Exception) -> None:
        log.warning("%s: UDP receive error: %s", self._tracker.name, exc)
