"""systemd notification (sd_notify) without a library: one datagram per message to ``$NOTIFY_SOCKET``.

``READY=1`` once the devices are connected, ``STATUS=...`` lines, and ``WATCHDOG=1`` sent from an asyncio
task at half of ``$WATCHDOG_USEC``: a blocked event loop stops the pings and systemd restarts the service.
Outside systemd (no ``$NOTIFY_SOCKET``) every call is a no-op.
"""

from __future__ import annotations

import asyncio
import logging
import os
import socket
import time
from collections import deque

log = logging.getLogger(__name__)


class Notifier:
    """Sends notify messages to the socket named by ``environ['NOTIFY_SOCKET']`` (path or ``@abstract``)."""

    def __init__(self, environ: dict[str, str] | None = None):
        env = os.environ if environ is None else environ
        self.address = env.get("NOTIFY_SOCKET") or None
        self.watchdog_s = _watchdog_interval_s(env)
        self.ping_times_s: deque[float] = deque(maxlen=10000)

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def send(self, *lines: str) -> bool:
        """Send ``lines`` as one message; returns False (and logs) when it cannot be delivered."""
        if not self.address:
            return False
        addr = "\0" + self.address[1:] if self.address.startswith("@") else self.address
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as s:
                s.connect(addr)
                s.sendall("\n".join(lines).encode())
        except OSError as e:
            log.warning("sd_notify to %s failed: %s", self.address, e)
            return False
        return True

    def ready(self, status: str | None = None) -> bool:
        return self.send("READY=1", *([f"STATUS={status}"] if status else []))

    def status(self, text: str) -> bool:
        return self.send(f"STATUS={text}")

    def stopping(self) -> bool:
        return self.send("STOPPING=1")

    async def watchdog_loop(self) -> None:
        """Ping ``WATCHDOG=1`` at half the watchdog interval from the event loop, forever (cancel to stop)."""
        if self.watchdog_s is None:
            return
        period = self.watchdog_s / 2.0
        while True:
            self.send("WATCHDOG=1")
            self.ping_times_s.append(time.monotonic())
            await asyncio.sleep(period)


def _watchdog_interval_s(env) -> float | None:
    """The watchdog interval (s) systemd asked for, or None (unset, zero, or meant for another process)."""
    usec = env.get("WATCHDOG_USEC")
    if not usec:
        return None
    pid = env.get("WATCHDOG_PID")
    if pid and pid.isdigit() and int(pid) != os.getpid():
        return None
    try:
        value = int(usec)
    except ValueError:
        log.warning("ignoring WATCHDOG_USEC=%r", usec)
        return None
    return value / 1e6 if value > 0 else None
