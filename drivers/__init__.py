"""Device interfaces, typed errors and the real drivers."""

from tandemscan.drivers.errors import (
    DeviceError,
    DeviceFault,
    DeviceTimeout,
    NotConnected,
    OutOfReach,
    SafetyStop,
    TargetNotVisible,
)
from tandemscan.drivers.interfaces import (
    Arm,
    Chassis,
    ChassisPose,
    Device,
    DeviceStatus,
    SafetyIO,
    SafetyState,
    ScanFrame,
    Scanner,
    Tracker,
    TrackerReading,
)

__all__ = [
    "Arm", "Chassis", "ChassisPose", "Device", "DeviceError", "DeviceFault", "DeviceStatus", "DeviceTimeout",
    "NotConnected", "OutOfReach", "SafetyIO", "SafetyStop", "SafetyState", "ScanFrame", "Scanner",
    "TargetNotVisible", "Tracker", "TrackerReading",
]
