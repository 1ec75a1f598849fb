"""The device registry: which class drives a device role, found through entry points (docs/architecture.md, the
cell layer; docs/howto/add-a-device-driver.md).

A driver is an entry point of group :data:`DEVICE_GROUP` named ``<role>.<driver>`` whose value names its class,
``"package.module:Class"``; the class is imported only when a cell or a configuration asks for it, as python-can
loads its interfaces. The package registers its own drivers this way in ``pyproject.toml``: ``<role>.real`` (the
built-in vendor's driver) and ``<role>.sim`` (the simulator's twin). A vendor's plugin registers
``<role>.<its name>``: a class built as ``Class(section, name=role)`` that names its own pydantic settings model
as ``Class.Settings`` (the section's ``[<role>.<its name>]`` table, validated by it, arrives as
``section.settings``), and, for hardware-in-the-loop cells, its emulator in :data:`EMULATOR_GROUP` under the same
name. The device sections of :class:`~tandemscan.config.models.CellConfig` are the roles. The simulator's own
sections (``[sim]``, ``[hil]``) are validated by the models it registers in :data:`SIMULATOR_GROUP`.
"""

from __future__ import annotations

import sys
from functools import lru_cache
from importlib.metadata import EntryPoint, distributions
from typing import TYPE_CHECKING, Annotated

from pydantic import Field

if TYPE_CHECKING:
    from tandemscan.config.models import CellConfig

DEVICE_GROUP = "tandemscan.devices"
EMULATOR_GROUP = "tandemscan.emulators"
#: the simulator's own settings models, by the section of the cell configuration they validate (``sim``, ``hil``)
SIMULATOR_GROUP = "tandemscan.simulator"
#: the roles every cell has
ROLES = ("measure_chassis", "tracking_chassis", "arm", "scanner", "tracker", "safety")
#: the roles a cell has where its section says ``enabled`` (the measurement AGV's lifting column)
OPTIONAL_ROLES = ("lift",)
#: the drivers whose settings are the section's own fields: the simulator's twin and the built-in vendor's driver
BUILT_IN_DRIVERS = ("sim", "real")

#: the ``driver`` of a device section: ``"sim"``, ``"real"`` or the name a plugin registered for the role
DriverKind = Annotated[str, Field(pattern=r"^[a-z][a-z0-9_]*$",
                                  description='"sim", "real" or a plugin\'s driver registered for the role')]


def cell_roles(config: CellConfig) -> tuple[str, ...]:
    """The device roles of ``config``'s cell: every cell's, and the optional ones its section enables."""
    return ROLES + tuple(role for role in OPTIONAL_ROLES if getattr(config, role).enabled)


def registered(group: str, role: str) -> dict[str, EntryPoint]:
    """The entry points of ``group`` registered for ``role``, by driver name."""
    prefix = f"{role}."
    found: dict[str, EntryPoint] = {}
    for ep in _group(group, tuple(sys.path)):
        if ep.name.startswith(prefix):
            found.setdefault(ep.name.removeprefix(prefix), ep)
    return found


@lru_cache(maxsize=8)
def _group(group: str, search_path: tuple[str, ...]) -> tuple[EntryPoint, ...]:
    """The entry points of ``group`` of every distribution on ``search_path`` (``sys.path``), in its order (the
    first of a name wins where a registry is built from them): also those of a copy of a distribution that an
    earlier one shadows, so that an editable install whose metadata predates its entry points still finds them in
    the shared environment's copy. Read once per ``search_path``, as a scan reads every installed distribution
    (about 20 ms here); a plugin installed while a process runs is seen once sys.path changes, or by the next
    process."""
    return tuple(ep for dist in distributions() for ep in dist.entry_points.select(group=group))


def load_registered(group: str, role: str, driver: str) -> object:
    """The object ``group`` registers as ``<role>.<driver>``, imported now; ValueError naming the registered ones
    where there is none."""
    found = registered(group, role)
    if driver not in found:
        known = ", ".join(sorted(found)) or f"none: is the package installed (pip install -e .), with its {group}?"
        raise ValueError(f"{role}: no driver {driver!r} registered in {group} (registered: {known})")
    return found[driver].load()


def device_class(role: str, driver: str) -> type:
    """The class registered as driver ``driver`` of ``role``; ValueError where none is."""
    return load_registered(DEVICE_GROUP, role, driver)


def plugin_settings_model(roles: tuple[str, ...], driver: str) -> type:
    """The pydantic model of a plugin's settings (``Class.Settings``) for its driver ``driver`` of the first of
    ``roles`` (a section that serves several roles) that registers it; ValueError where none does."""
    role = next((r for r in roles if driver in registered(DEVICE_GROUP, r)), roles[0])
    cls = device_class(role, driver)
    if not hasattr(cls, "Settings"):
        raise ValueError(f"{role}: the plugin's driver {driver!r} names no Settings model")
    return cls.Settings


def simulator_settings_model(section: str) -> type:
    """The pydantic model the simulator registers in :data:`SIMULATOR_GROUP` for its section ``section`` of the
    cell configuration (``sim``, ``hil``), imported now; ValueError where none is."""
    for ep in _group(SIMULATOR_GROUP, tuple(sys.path)):
        if ep.name == section:
            return ep.load()
    raise ValueError(f"no settings model registered for [{section}] in {SIMULATOR_GROUP}: is the package installed "
                     "(pip install -e .)?")
