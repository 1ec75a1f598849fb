"""Typed device errors. Every error names the device it came from."""

from __future__ import annotations


class DeviceError(Exception):
    """Base of all device errors; ``device`` is the configured device name (e.g. ``"tracker"``)."""

    def __init__(self, device: str, message: str):
        super().__init__(f"{device}: {message}")
        self.device = device
        self.reason = message


class NotConnected(DeviceError):
    """A verb was called before ``connect()`` or after the link dropped."""


class DeviceTimeout(DeviceError):
    """The device did not answer or finish within its timeout."""


class DeviceFault(DeviceError):
    """The device reported a fault (error code, driver fault, invalid reply)."""


class SafetyStop(DeviceError):
    """Motion refused or halted by a safety stop (e-stop, light curtain, protective stop)."""


class TargetNotVisible(DeviceFault):
    """The tracker cannot measure the target: outside its field of view, beyond range, or occluded."""


class OutOfReach(DeviceFault):
    """The arm cannot reach a commanded pose, or a joint target is outside its limits."""
