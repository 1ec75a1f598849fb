"""Building a cell's devices from the device registry (:mod:`tandemscan.config.device_registry`: entry points of group
``tandemscan.devices``, ``<role>.<driver>`` = ``"module:Class"``).

A class is imported only when a cell asks for it (as python-can loads its interfaces), so no product module
imports ``sim_drivers`` to build a cell, and a real cell never imports the simulator. Roles are the device
sections of :class:`~tandemscan.config.models.CellConfig`; a section's ``driver`` (``"real"``, ``"sim"`` or a
plugin's name) picks the entry. The simulated world behind the ``"sim"`` twins and the hardware-in-the-loop
emulators is :data:`SIMULATION`, loaded the same way (``docs/architecture.md``, the cell layer).
"""

from __future__ import annotations

import importlib

from tandemscan.config.device_registry import OPTIONAL_ROLES, ROLES, device_class
from tandemscan.config.models import CellConfig
from tandemscan.drivers.interfaces import Device

__all__ = ["ROLES", "SIMULATION", "build_real_device", "device_class", "load_entry"]

#: the simulated cell (world, twins' construction, emulators, ground-truth observer), where any role is "sim"
#: or ``[hil] enabled``
SIMULATION = "tandemscan.sim_drivers.cell:Simulation"


def load_entry(spec: str) -> type:
    """The class named ``"package.module:Class"``, imported now."""
    module, _, name = spec.partition(":")
    return getattr(importlib.import_module(module), name)


def build_real_device(role: str, config: CellConfig) -> Device:
    """The driver of ``role`` that its config section names (a built-in vendor's or a plugin's, never the
    simulator's twin), built from the section and named after the role (errors then say e.g.
    ``measure_chassis: ...``); ValueError for an unknown role or where that driver is not registered."""
    if role not in ROLES + OPTIONAL_ROLES:
        raise ValueError(f"unknown device role {role!r}; expected one of {', '.join(ROLES + OPTIONAL_ROLES)}")
    section = getattr(config, role)
    return device_class(role, section.driver)(section, name=role)
