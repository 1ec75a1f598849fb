"""Build the cell's devices from the configuration: a twin or a real driver per device."""

from __future__ import annotations

from dataclasses import dataclass

from tandemscan.config.models import CellConfig
from tandemscan.drivers.factory import ROLES, build_real_device
from tandemscan.drivers.interfaces import Arm, Chassis, Device, Lift, SafetyIO, Scanner, Tracker
from tandemscan.sim_drivers.hil import HilEmulators
from tandemscan.sim_drivers.lift import SimLift
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
    emulators: HilEmulators | None = None
    lift: Lift | None = None  # the measurement AGV's lifting column, where it has one

    def devices(self) -> list[Device]:
        devices = [self.measure_chassis, self.tracking_chassis, self.arm, self.scanner, self.tracker, self.safety]
        return devices + ([self.lift] if self.lift is not None else [])

    async def connect(self) -> None:
        """Start the emulators (hardware-in-the-loop), then connect every device; on failure close them all."""
        try:
            if self.emulators is not None:
                await self.emulators.start()
            for d in self.devices():
                await d.connect()
        except BaseException:
            await self.close()
            raise

    async def close(self) -> None:
        for d in self.devices():
            await d.close()
        if self.emulators is not None:
            await self.emulators.stop()


def build_cell(config: CellConfig, world: SimWorld | None = None, *, scan_process: bool = False) -> Cell:
    """Devices per ``config``: a twin or the real driver per role (``driver``); twins and hardware-in-the-loop
    emulators share ``world`` (made from the config when needed and not given). ``scan_process``: the scanner
    twin casts its rays in a worker process (the daemon, whose event loop must not block)."""
    real = {role for role in ROLES if getattr(config, role).driver == "real"}
    if config.hil.enabled and real:
        config = _odometry_from_sim_start(config, real)
    if world is None and (len(real) < len(ROLES) or config.hil.enabled):
        world = SimWorld(config)
    twins = {
        "measure_chassis": lambda: SimChassis("measure_chassis", world, SimWorld.MEASURE_ROBOT),
        "tracking_chassis": lambda: SimChassis("tracking_chassis", world, SimWorld.TRACKING_ROBOT),
        "arm": lambda: SimArm("arm", world),
        "scanner": lambda: SimScanner("scanner", world, out_of_process=scan_process),
        "tracker": lambda: SimTracker("tracker", world),
        "safety": lambda: SimSafetyIO("safety", world),
    }
    devices = {role: build_real_device(role, config) if role in real else twins[role]() for role in ROLES}
    emulators = HilEmulators(config, world) if config.hil.enabled and world is not None else None
    return Cell(**devices, world=world, emulators=emulators, lift=_lift(config, world))


def _lift(config: CellConfig, world: SimWorld | None) -> Lift | None:
    """The lifting column per ``[lift]``: none, or its twin (no real column driver exists yet)."""
    if not config.lift.enabled:
        return None
    if config.lift.driver == "real" or world is None:
        raise CellBuildError("[lift] driver = 'real': no driver for a real lifting column exists yet (use 'sim')")
    return SimLift("lift", world)


def _odometry_from_sim_start(config: CellConfig, real: set[str]) -> CellConfig:
    """In a hardware-in-the-loop cell the chassis odometry starts at the simulated start poses, as the twins'."""
    update = {}
    for role, start in (("measure_chassis", config.sim.measure_start), ("tracking_chassis", config.sim.tracking_start)):
        if role in real:
            section = getattr(config, role)
            can = section.can.model_copy(update={"odometry_start_x_mm": start.x_mm, "odometry_start_y_mm": start.y_mm,
                                                 "odometry_start_heading_deg": start.heading_deg})
            update[role] = section.model_copy(update={"can": can})
    return config.model_copy(update=update)
