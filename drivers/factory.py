"""Build the real driver of one device role from the cell configuration (``driver = "real"``).

``build_cell`` calls :func:`build_real_device` for each role whose section says ``driver = "real"``; twins
stay in ``sim_drivers``. Roles are the device sections of :class:`~tandemscan.config.models.CellConfig`.
"""

from __future__ import annotations

from tandemscan.config.models import CellConfig
from tandemscan.drivers.agv_can import AgvCanChassis
from tandemscan.drivers.interfaces import Device
from tandemscan.drivers.jaka_tcp import JakaTcpArm
from tandemscan.drivers.metronor import MetronorTracker
from tandemscan.drivers.phoxi import PhoxiScanner
from tandemscan.drivers.safety_modbus import ModbusSafetyIO

ROLES = ("measure_chassis", "tracking_chassis", "arm", "scanner", "tracker", "safety")


def build_real_device(role: str, config: CellConfig) -> Device:
    """The real driver for ``role``, named after it (errors then say e.g. ``measure_chassis: ...``)."""
    if role in ("measure_chassis", "tracking_chassis"):
        return AgvCanChassis(getattr(config, role), name=role)
    if role == "arm":
        return JakaTcpArm(config.arm, name=role)
    if role == "scanner":
        return PhoxiScanner(config.scanner, name=role)
    if role == "tracker":
        return MetronorTracker(config.tracker, name=role)
    if role == "safety":
        return ModbusSafetyIO(config.safety, name=role)
    raise ValueError(f"unknown device role {role!r}; expected one of {', '.join(ROLES)}")
