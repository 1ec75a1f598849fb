"""Motion as a capability (docs/architecture.md, "The motion gate").

A robot's motion commands are reachable only through the handle the gate hands out for one block::

    async with session.gate.motion(Robot.MEASURE) as robot:
        await robot.arm.move_joints(q, timeout_s)

Everywhere else the cell shows its movers (both chassis, the arm, the lifting column) through their readings
(``cell.arm.joints()``); asking one of them for a motion command raises :class:`NoMotionCapability` before the
device is reached, and so does a handle used after its block has ended. The raw movers live in :class:`Movers`,
which only the session's gate reads.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Any, cast

from tandemscan.drivers.interfaces import (
    Arm,
    Chassis,
    Device,
    Lift,
)


class Robot(StrEnum):
    """The cell's two robots, as the gate and the supervisor name them."""

    MEASURE = "measure"     # measurement AGV, arm and (where fitted) lifting column
    TRACKING = "tracking"   # tracking AGV carrying the tracker


class NoMotionCapability(AttributeError):
    """A motion command asked for without the gate's handle (or with one whose block has ended)."""


def protocol_members(protocol: type) -> frozenset[str]:
    """The public names a ``typing.Protocol`` declares, its bases' included (methods and attributes)."""
    names: set[str] = set()
    for cls in protocol.__mro__:
        if getattr(cls, "_is_protocol", False) and cls.__module__ != "typing":
            names |= {n for n in vars(cls) if not n.startswith("_")}
            names |= {n for n in getattr(cls, "__annotations__", {}) if not n.startswith("_")}
    return frozenset(names)


class DeviceView:
    """``device`` seen through the names in ``reachable`` only; any other attribute raises
    :class:`NoMotionCapability` saying ``why``. :meth:`revoke` empties ``reachable`` (a handle whose block ended).
    """

    __slots__ = ("_device", "_reachable", "_why")

    def __init__(self, device: Any, reachable: frozenset[str], why: str):
        self._device, self._reachable, self._why = device, reachable, why

    def __getattr__(self, name: str) -> Any:
        if name in self._reachable:
            return getattr(self._device, name)
        raise NoMotionCapability(f"{self._device.name}.{name} is not reachable here: {self._why}")

    def revoke(self, why: str) -> None:
        self._reachable, self._why = frozenset(), why

    def __repr__(self) -> str:
        return f"<{type(self._device).__name__} {self._device.name!r} through {sorted(self._reachable)}>"


OUTSIDE_THE_GATE = "move it inside `async with gate.motion(Robot...) as robot`"
LIFECYCLE = protocol_members(Device) | {"stop"}   # what the supervisor needs: connect, close, status, stop


def readings(device: Any, protocol: type) -> Any:
    """``device`` through the readings ``protocol`` declares (``ArmReadings``, ``ChassisReadings``, ...)."""
    return DeviceView(device, protocol_members(protocol), OUTSIDE_THE_GATE)


@dataclass(frozen=True)
class MeasureRobot:
    """The measurement robot inside its motion block: chassis, arm and lifting column (None where not fitted)."""

    chassis: Chassis
    arm: Arm
    lift: Lift | None


@dataclass(frozen=True)
class TrackingRobot:
    """The tracking robot inside its motion block: its chassis."""

    chassis: Chassis


class Movers:
    """The devices that move, per robot; read only by the session's gate (:meth:`grant`) and its supervisor
    (:meth:`lifecycle`, :meth:`stoppable`)."""

    def __init__(self, measure_chassis: Chassis, tracking_chassis: Chassis, arm: Arm, lift: Lift | None):
        self._devices: dict[Robot, list[Any]] = {
            Robot.MEASURE: [measure_chassis, arm] + ([lift] if lift is not None else []),
            Robot.TRACKING: [tracking_chassis]}

    def lifecycle(self) -> list[Device]:
        """Every mover through its lifecycle and ``stop`` only (the supervisor's connect, status, halt)."""
        return [cast(Device, DeviceView(d, LIFECYCLE, "the supervisor only connects, polls and stops"))
                for ds in self._devices.values() for d in ds]

    def stoppable(self) -> dict[str, list[Device]]:
        """Per robot, its movers through lifecycle and ``stop`` (the supervisor's emergency path)."""
        return {robot: [cast(Device, DeviceView(d, LIFECYCLE, "the supervisor only connects, polls and stops"))
                        for d in ds] for robot, ds in self._devices.items()}

    def grant(self, robot: Robot) -> tuple[MeasureRobot | TrackingRobot, list[DeviceView]]:
        """The handle of ``robot`` for one motion block, and its views to revoke when the block ends."""
        views = [DeviceView(d, frozenset(dir(d)), OUTSIDE_THE_GATE) for d in self._devices[robot]]
        if robot == Robot.TRACKING:
            return TrackingRobot(cast(Chassis, views[0])), views
        lift = cast(Lift, views[2]) if len(views) > 2 else None
        return MeasureRobot(cast(Chassis, views[0]), cast(Arm, views[1]), lift), views

