"""The async interface of every device kind (docs/architecture.md, "Layers"; docs/drivers.md).

A real driver and its simulated twin implement the same Protocol; the configuration picks which one.
Every verb takes or applies a timeout and raises the typed errors of :mod:`tandemscan.drivers.errors`.
Units: mm and rad; ``T_a_b`` 4x4 float64 matrices.

A device that moves has two protocols: its readings (``ArmReadings``: joints, flange pose) and the device
(``Arm``: the readings and the motion commands). The cell shows its movers through their readings only; the
motion commands come with the motion gate's handle (docs/architecture.md, "The motion gate").
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Protocol, runtime_checkable

import numpy as np

# ---------------------------------------------------------------- status snapshots and data


class DeviceState(StrEnum):
    """What a device is doing, as its status reports it (serialised as the lower-case word)."""

    DISCONNECTED = "disconnected"
    IDLE = "idle"
    MOVING = "moving"
    BUSY = "busy"   # working without moving (a scanner capturing)
    FAULT = "fault"
    STOPPED = "stopped"   # held by a safety stop or an e-stop input


@dataclass(frozen=True)
class DeviceStatus:
    """A snapshot of one device."""

    name: str
    connected: bool
    state: DeviceState
    detail: dict[str, object] = field(default_factory=dict)


@dataclass(frozen=True)
class ChassisPose:
    """A chassis pose on the floor in its odometry frame: position (mm) and heading (rad)."""

    x_mm: float
    y_mm: float
    heading_rad: float


@dataclass(frozen=True)
class ScanFrame:
    """One scanner capture in the scanner frame S: points (N, 3) mm, optional normals and confidence."""

    points_mm: np.ndarray
    normals: np.ndarray | None
    confidence: np.ndarray | None
    timestamp_s: float


@dataclass(frozen=True)
class TrackerReading:
    """One tracker measurement of the target: ``T_C_T`` (mm), its 6x6 covariance and timestamps.

    Covariance order: translation x, y, z (mm^2) then rotation vector x, y, z (rad^2), in the camera frame.
    """

    T_C_T: np.ndarray
    covariance: np.ndarray
    timestamp_s: float
    frame_number: int


@dataclass(frozen=True)
class SafetyState:
    """Cell safety inputs: any true ``estop`` or ``light_curtain_broken`` means no motion."""

    estop: bool
    light_curtain_broken: bool
    target_light_on: bool

    @property
    def motion_allowed(self) -> bool:
        return not (self.estop or self.light_curtain_broken)


# ---------------------------------------------------------------- device protocols


@runtime_checkable
class Device(Protocol):
    """What every device has: a name, a lifecycle and a status snapshot."""

    name: str

    async def connect(self) -> None: ...

    async def close(self) -> None: ...

    async def status(self) -> DeviceStatus: ...


@runtime_checkable
class ChassisReadings(Device, Protocol):
    """What anyone may ask an AGV chassis: where its odometry says it stands."""

    async def odometry(self) -> ChassisPose: ...


@runtime_checkable
class Chassis(ChassisReadings, Protocol):
    """An AGV chassis with skid steering; moves are closed-loop on its own odometry."""

    async def move_to(self, target: ChassisPose, timeout_s: float | None = None) -> ChassisPose:
        """Drive to ``target`` (odometry frame); returns the odometry pose on arrival."""
        ...

    async def set_odometry(self, pose: ChassisPose) -> None:
        """Re-localise the odometry: the chassis stands at ``pose`` (mm, rad) in its odometry frame from now on
        (where the journal left it, once the tracker confirmed it did not move while the daemon was down)."""
        ...

    async def stop(self) -> None:
        """Zero velocity at once (emergency path)."""
        ...


@runtime_checkable
class ArmReadings(Device, Protocol):
    """What anyone may ask a six-axis arm: joint angles (rad) and flange pose ``T_B_E`` (mm)."""

    async def joints(self) -> np.ndarray: ...

    async def flange_pose(self) -> np.ndarray:
        """``T_B_E`` as the controller reports it (mm)."""
        ...


@runtime_checkable
class Arm(ArmReadings, Protocol):
    """A six-axis arm: joint angles in rad, flange pose ``T_B_E`` in mm."""

    async def enable(self) -> None:
        """Power on and enable the servos."""
        ...

    async def move_joints(self, joints_rad: np.ndarray, timeout_s: float | None = None) -> None:
        """Joint move; returns when the arm is in position."""
        ...

    async def stop(self) -> None: ...


@runtime_checkable
class Scanner(Device, Protocol):
    """A structured-light 3D scanner."""

    async def capture(self, timeout_s: float | None = None) -> ScanFrame: ...


@runtime_checkable
class Tracker(Device, Protocol):
    """An optical tracker measuring the 6-DoF pose of the target."""

    async def read_pose(self, timeout_s: float | None = None) -> TrackerReading:
        """One reading; raises :class:`TargetNotVisible` when the target cannot be measured."""
        ...


@runtime_checkable
class SafetyIO(Device, Protocol):
    """Cell safety inputs and signal outputs."""

    async def read(self) -> SafetyState: ...

    async def set_target_light(self, on: bool) -> None: ...


SafetyListener = Callable[[SafetyState], None]


@runtime_checkable
class PushesSafetyChanges(Protocol):
    """A safety I/O that polls its inputs itself (a Modbus module) and tells listeners of each change as its reply
    arrives, so the supervisor reads it at once instead of at its next control tick. A twin read on demand has
    nothing to push and does not implement it."""

    def add_listener(self, listener: SafetyListener) -> None:
        """Call ``listener(state)`` on the event loop whenever the polled state changes."""
        ...


@runtime_checkable
class LiftReadings(Device, Protocol):
    """What anyone may ask a lifting column: its height now (mm)."""

    async def height(self) -> float:
        """The column's height now (mm)."""
        ...


@runtime_checkable
class Lift(LiftReadings, Protocol):
    """A lifting column under the arm on the measurement AGV: one vertical axis, height in mm above the
    arm's mount (``T_V2_B`` with z raised by the height, :func:`pipeline.kinematics.arm_base_on_column`)."""

    async def move_to(self, height_mm: float, timeout_s: float | None = None) -> float:
        """Drive to ``height_mm``; returns the height reached (mm). Raises :class:`OutOfReach` outside its range."""
        ...

    async def stop(self) -> None:
        """Stop the axis at once (emergency path)."""
        ...
