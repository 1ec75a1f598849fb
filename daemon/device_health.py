"""What the supervisor knows of one device's health, as published to the console and the MES (``device`` events)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from tandemscan.drivers.interfaces import DeviceState


@dataclass
class DeviceHealth:
    """What the supervisor knows about one device (published on every change); ``next_retry_s``: when the next
    reconnect try is due (``time.monotonic()``, s), None when none is scheduled."""

    name: str
    connected: bool = False
    state: DeviceState = DeviceState.DISCONNECTED
    detail: dict = field(default_factory=dict)
    last_error: str | None = None
    reconnects: int = 0
    next_retry_s: float | None = None

    @property
    def up(self) -> bool:
        """Connected and not reporting a fault: a device a job can use."""
        return self.connected and self.state != DeviceState.FAULT

    def as_dict(self) -> dict:
        return {"name": self.name, "connected": self.connected, "state": self.state, "detail": self.detail,
                "last_error": self.last_error, "reconnects": self.reconnects}


def fault_reason(detail: Mapping) -> str:
    """The reason a device's own fault status gives (its ``error`` or ``fault`` detail)."""
    return str(detail.get("error") or detail.get("fault") or "the device reports a fault")
