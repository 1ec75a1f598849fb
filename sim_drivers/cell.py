"""Build the cell's devices from the configuration: a twin or a real driver per device."""

from __future__ import annotations

from dataclasses import dataclass

from tandemscan.config.models import CellConfig
from tandemscan.drivers.interfaces import Arm, Chassis, Device, SafetyIO, Scanner, Tracker
from tandemscan.sim_drivers.twins import SimArm, SimChassis, SimSafetyIO, SimScanner, SimTracker
from tandemscan.sim_drivers.world import SimWorld


class CellBuildError(Exception):
    """The configuration asks for a device that cannot be built."""


@dataclass
class Cell:
    """The devices of one cell, and the simulated world when any device is a twin."""

    measure_chassis: Chassis
    tracking_chassis: Chassis
    arm: Arm
    scanner: Scanner
    tracker: Tracker
    safety: SafetyIO
    world: SimWorld | None

    def devices(self) -> list[Device]:
        return [self.measure_chassis, self.tracking_chassis, self.arm, self.scanner, self.tracker, self.safety]

    async def connect(self) -> None:
        for d in self.devices():
            await d.connect()

    async def close(self) -> None:
        for d in self.devices():
            await d.close()


def build_cell(config: CellConfig, world: SimWorld | None = None) -> Cell:
    """Devices per ``config``; twins share ``world`` (made from the config when not given)."""
    real = [n for n in ("measure_chassis", "tracking_chassis", "arm", "scanner", "tracker", "safety")
            if getattr(config, n).driver == "real"]
    if real:
        raise CellBuildError(f"real drivers are not part of this build yet: {', '.join(real)} (use driver = \"sim\")")
    world = world or SimWorld(config)
    return Cell(
        measure_chassis=SimChassis("measure_chassis", world, SimWorld.MEASURE_ROBOT),
        tracking_chassis=SimChassis("tracking_chassis", world, SimWorld.TRACKING_ROBOT),
        arm=SimArm("arm", world),
        scanner=SimScanner("scanner", world),
        tracker=SimTracker("tracker", world),
        safety=SimSafetyIO("safety", world),
        world=world,
    )
