"""Tracker pose-stream emulator: frames at a fixed rate over TCP (any number of clients), a serial line (the
master side of a pty in tests) or UDP datagrams to one address, encoded by the same adapter the driver
parses with, in any of its framings and record layouts.

Like comparable trackers (NDI ``TSTART`` / ``BX``), a TCP client may have to ask: with ``requires_start`` it
gets nothing before it sent the configured ``start_command``; with a configured ``poll_command`` it gets one
frame per poll.

The pose comes from ``source()``, which returns ``(T_C_T mm, 6x6 covariance)`` or raises
:class:`~tandemscan.drivers.errors.TargetNotVisible` (``SimWorld.measure_target`` has this shape).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from tandemscan.config.models import TrackerStreamConfig
from tandemscan.drivers.errors import TargetNotVisible
from tandemscan.drivers.pose_stream import PoseStreamAdapter
from tandemscan.drivers.tasks import cancel_and_wait
from tandemscan.sim_drivers.emulators.tcp_server import TcpService

log = logging.getLogger(__name__)

PoseSource = Callable[[], tuple[np.ndarray, np.ndarray]]


@dataclass
class TrackerFaults:
    """Fault injection; flags may change while the emulator runs."""

    stall: bool = False  # no frames at all
    drop_fraction: float = 0.0  # this fraction of frames is lost
    corrupt_next: bool = False  # the next frame has a wrong checksum
    nan_next: bool = False  # the next frame carries a NaN position (with a valid checksum)
    truncate_next: bool = False  # the next frame is cut in half, then the stream resumes
    burst: int = 1  # frames go out this many at a time, in one write (a network that delivers late, at once)


class _Client:
    """One TCP client: how to write to it, whether it sent the start command, polls not yet answered."""

    def __init__(self, write: Callable[[bytes], None], started: bool):
        self.write, self.started, self.polls = write, started, 0


def fixed_pose_source(T_C_T: np.ndarray, sigma_mm: float = 0.01, sigma_rad: float = 2e-5) -> PoseSource:
    """A scripted source: always ``T_C_T`` with the given 1-sigma uncertainty (no noise added)."""
    cov = np.diag([sigma_mm**2] * 3 + [sigma_rad**2] * 3)
    return lambda: (np.array(T_C_T, float), cov)


class TrackerStreamEmulator:
    """Streams frames at ``rate_hz``; ``start_tcp()`` or ``start_serial(fd)``, then ``stop()``."""

    def __init__(self, cfg: TrackerStreamConfig, source: PoseSource, rate_hz: float = 60.0, seed: int = 0,
                 requires_start: bool = False):
        self.cfg = cfg
        self.requires_start = requires_start
        self.adapter = PoseStreamAdapter(cfg)
        self.source = source
        self.period_s = 1.0 / rate_hz
        self.faults = TrackerFaults()
        self.frames_sent = 0
        self._rng = np.random.default_rng(seed)
        self.device_times: dict[int, float] = {}  # frame number -> device time (s) of every frame sent
        self._tcp: TcpService | None = None
        self._clients: list[_Client] = []
        self._udp: asyncio.DatagramTransport | None = None
        self._task: asyncio.Task | None = None
        self._pending: list[bytes] = []  # frames of a burst not yet written

    async def start_tcp(self, host: str = "127.0.0.1", port: int = 0) -> int:
        """Serve TCP clients; returns the port."""
        self._tcp = TcpService(self._serve_client, host, port)
        port = await self._tcp.start()
        self._task = asyncio.create_task(self._run())
        return port

    async def start_serial(self, fd: int) -> None:
        """Write the stream to the file descriptor ``fd`` (a pty master)."""
        os.set_blocking(fd, False)

        def write(data: bytes) -> None:
            with contextlib.suppress(BlockingIOError, OSError):
                os.write(fd, data)

        self._clients.append(_Client(write, started=True))
        self._task = asyncio.create_task(self._run())

    async def start_udp(self, host: str, port: int) -> None:
        """Send every frame as a datagram to ``host:port`` (where the driver listens)."""
        self._udp, _ = await asyncio.get_running_loop().create_datagram_endpoint(
            asyncio.DatagramProtocol, remote_addr=(host, port))
        self._clients.append(_Client(self._udp.sendto, started=True))
        self._task = asyncio.create_task(self._run())

    async def drop_connections(self) -> None:
        if self._tcp is not None:
            await self._tcp.drop_clients()

    async def stop(self) -> None:
        await cancel_and_wait(self._task)
        self._task = None
        if self._tcp is not None:
            await self._tcp.stop()
            self._tcp = None
        if self._udp is not None:
            self._udp.close()
            self._udp = None

    async def _serve_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        client = _Client(writer.write, started=not self.requires_start)
        self._clients.append(client)
        start, poll = self.cfg.start_command.encode(), self.cfg.poll_command.encode()
        tail = max(len(start), len(poll)) - 1  # bytes kept between reads: a command split across them
        received = b""
        try:
            while data := await reader.read(1024):  # EOF ends the client
                received += data
                if start and start in received:
                    client.started = True
                if poll:
                    client.polls += received.count(poll)
                received = received[len(received) - tail :] if tail > 0 else b""
        finally:
            self._clients.remove(client)

    def next_frame(self) -> bytes:
        """Encode the next frame from the source, applying one-shot faults."""
        self.frames_sent += 1
        t = asyncio.get_running_loop().time()
        try:
            T, cov = self.source()
        except TargetNotVisible:
            T, cov = None, None
        if self.faults.nan_next and T is not None:
            self.faults.nan_next = False
            T = np.array(T, float)
            T[0, 3] = np.nan
        self.device_times[self.frames_sent] = t
        raw = self.adapter.encode(self.frames_sent, t, T, cov)
        if self.faults.corrupt_next:
            self.faults.corrupt_next = False
            raw = raw[:-4] + (b"00" if raw[-4:-2] != b"00" else b"11") + raw[-2:]
        if self.faults.truncate_next:
            self.faults.truncate_next = False
            raw = raw[: len(raw) // 2]
        return raw

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        next_t = loop.time()
        while True:
            next_t += self.period_s
            await asyncio.sleep(max(0.0, next_t - loop.time()))
            if self.faults.stall or not self._clients:
                continue
            if self.faults.drop_fraction and self._rng.random() < self.faults.drop_fraction:
                self.frames_sent += 1
                continue
            self._pending.append(self.next_frame())
            if len(self._pending) < self.faults.burst:
                continue
            frames, self._pending = b"".join(self._pending), []
            for client in list(self._clients):
                if self.cfg.poll_command:
                    if client.polls > 0:
                        client.polls -= 1
                        client.write(frames)
                elif client.started:
                    client.write(frames)
