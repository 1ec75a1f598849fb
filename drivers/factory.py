"""The device registry: which class drives each device role, for a real cell and for the simulator.

The registry is data, ``{role: {"real": "module:Class", "sim": "module:Class"}}``, and a class is imported only
when a cell asks for it (as python-can loads its interfaces), so no product module imports ``sim_drivers`` to
build a cell, and a real cell never imports the simulator. Roles are the device sections of
:class:`~tandemscan.config.models.CellConfig`; a section's ``driver`` (``"real"`` or ``"sim"``) picks the entry.
The simulated world behind the ``"sim"`` twins and the hardware-in-the-loop emulators is :data:`SIMULATION`,
loaded the same way (``docs/architecture.md``, the cell layer).
"""

from __future__ import annotations

import importlib
from typing import Literal

from tandemscan.config.models import CellConfig
from tandemscan.drivers.interfaces import Device

DriverKind = Literal["real", "sim"]

DEVICE_REGISTRY: dict[str, dict[DriverKind, str]] = {
    "measure_chassis": {"real": "tandemscan.drivers.agv_can:AgvCanChassis",
                        "sim": "tandemscan.sim_drivers.twins:SimChassis"},
    "tracking_chassis": {"real": "tandemscan.drivers.agv_can:AgvCanChassis",
                         "sim": "tandemscan.sim_drivers.twins:SimChassis"},
    "arm": {"real": "tandemscan.drivers.jaka_tcp:JakaTcpArm", "sim": "tandemscan.sim_drivers.twins:SimArm"},
    "scanner": {"real": "tandemscan.drivers.phoxi:PhoxiScanner", "sim": "tandemscan.sim_drivers.twins:SimScanner"},
    "tracker": {"real": "tandemscan.drivers.metronor:MetronorTracker",
                "sim": "tandemscan.sim_drivers.twins:SimTracker"},
    "safety": {"real": "tandemscan.drivers.safety_modbus:ModbusSafetyIO",
               "sim": "tandemscan.sim_drivers.twins:SimSafetyIO"},
    # the measurement AGV's lifting column, built only where ``[lift] enabled``; no real column driver exists yet
    "lift": {"sim": "tandemscan.sim_drivers.lift:SimLift"},
}
#: the roles every cell has; the lift is optional
ROLES = tuple(role for role in DEVICE_REGISTRY if role != "lift")
#: the simulated cell (world, twins' construction, emulators, ground-truth observer), where any role is "sim"
#: or ``[hil] enabled``
SIMULATION = "tandemscan.sim_drivers.cell:Simulation"


def load_entry(spec: str) -> type:
    """The class named by a registry entry ``"package.module:Class"``, imported now."""
    module, _, name = spec.partition(":")
    return getattr(importlib.import_module(module), name)


def device_class(role: str, kind: DriverKind) -> type:
    """The class of ``kind`` registered for ``role``; ValueError for an unknown role."""
    if role not in DEVICE_REGISTRY:
        raise ValueError(f"unknown device role {role!r}; expected one of {', '.join(DEVICE_REGISTRY)}")
    if kind not in DEVICE_REGISTRY[role]:
        raise ValueError(f"{role}: no {kind} driver exists (use driver = 'sim')")
    return load_entry(DEVICE_REGISTRY[role][kind])


def build_real_device(role: str, config: CellConfig) -> Device:
    """The real driver for ``role`` from its config section, named after the role (errors then say e.g.
    ``measure_chassis: ...``)."""
    cls = device_class(role, "real")
    return cls(getattr(config, role), name=role)
