"""The neutral cell layer: the devices of one cell built from the configuration through the device registry.

Each role's class comes from the device registry (:mod:`tandemscan.config.device_registry`, entry points), imported
only when asked for. Where any role is simulated or ``[hil] enabled``, the simulated world behind the twins and
emulators is the registry's :data:`~tandemscan.drivers.factory.SIMULATION`; the product sees it only as a
:class:`CellSimulation`: something to start and stop around the devices and an observer of jobs
(``docs/architecture.md``, the cell layer). Motion always goes through the motion gate of a
:class:`~tandemscan.daemon.cell.session.CellSession` (:mod:`tandemscan.daemon.cell.motion`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

from tandemscan.config.device_registry import cell_roles
from tandemscan.config.models import CellConfig
from tandemscan.daemon.cell.motion import Movers, readings
from tandemscan.daemon.cell.observer import CalibrationObserver, JobObserver
from tandemscan.drivers.factory import SIMULATION, build_real_device, load_entry
from tandemscan.drivers.interfaces import (
    Arm,
    ArmReadings,
    Chassis,
    ChassisReadings,
    Device,
    Lift,
    LiftReadings,
    SafetyIO,
    Scanner,
    Tracker,
)


class CellBuildError(Exception):
    """The configuration asks for a device that cannot be built."""


class CellSimulation(Protocol):
    """What the product knows of a simulated cell: its lifecycle and its observers; never its truth.

    ``config`` is the configuration the real drivers are built from (with hardware in the loop, the chassis
    odometry starts where the simulated chassis stand)."""

    config: CellConfig

    def device(self, role: str) -> Device:
        """The twin of ``role``."""
        ...

    async def start(self) -> None:
        """Before the devices connect: restore the saved world state, start the hardware-in-the-loop emulators."""
        ...

    async def stop(self) -> None:
        """After the devices closed."""
        ...

    def job_observer(self, job_key: str, resumed: bool) -> JobObserver | None:
        """The ground-truth observer of the job ``job_key`` (a resumed one keeps what it observed so far); None
        where the cell's devices are all real drivers (hardware in the loop)."""
        ...

    def calibration_observer(self) -> CalibrationObserver:
        """The observer of a calibration job (it also sets up the simulated calibration plate)."""
        ...


class Cell:
    """The devices of one cell, and the simulation behind them where any device is simulated.

    The movers (both chassis, the arm and the lifting column, None where not fitted) are shown through their
    readings only (``cell.arm.joints()``, ``cell.tracking_chassis.odometry()``); their motion commands come with
    the handle of ``gate.motion(robot)`` (:mod:`tandemscan.daemon.cell.motion`)."""

    def __init__(self, *, measure_chassis: Chassis, tracking_chassis: Chassis, arm: Arm, scanner: Scanner,
                 tracker: Tracker, safety: SafetyIO, simulation: CellSimulation | None = None,
                 lift: Lift | None = None):
        """Eight parameters: the cell's six roles, its optional lifting column and the simulation behind them,
        each by name (keyword-only) as the device registry builds them (:func:`build_cell`)."""
        self.scanner, self.tracker, self.safety, self.simulation = scanner, tracker, safety, simulation
        self._movers = Movers(measure_chassis, tracking_chassis, arm, lift)
        self.measure_chassis: ChassisReadings = readings(measure_chassis, ChassisReadings)
        self.tracking_chassis: ChassisReadings = readings(tracking_chassis, ChassisReadings)
        self.arm: ArmReadings = readings(arm, ArmReadings)
        self.lift: LiftReadings | None = None if lift is None else readings(lift, LiftReadings)

    def devices(self) -> list[Device]:
        """Every device for the supervisor: the movers through their lifecycle and ``stop`` only."""
        return self._movers.lifecycle() + [self.scanner, self.tracker, self.safety]

    def motion_devices(self) -> dict[str, list[Device]]:
        """The devices that move, per robot (the measurement robot: its chassis, arm and column), through their
        lifecycle and ``stop`` only (the supervisor's emergency stop)."""
        return self._movers.stoppable()


def needs_simulation(config: CellConfig) -> bool:
    """Whether the cell of ``config`` has a simulated part: a twin, or emulators for the real drivers."""
    return config.hil.enabled or any(getattr(config, role).driver == "sim" for role in cell_roles(config))


def build_cell(config: CellConfig, *, scan_process: bool = False, state_file: Path | None = None,
               simulation: CellSimulation | None = None) -> Cell:
    """The devices of ``config``: per role the registry's driver that its section names (a vendor's, built-in or
    a plugin's) or the simulation's twin.

    ``scan_process``: a scanner twin casts its rays in a worker process (the daemon, whose event loop must not
    block). ``state_file``: where the simulated world keeps its state across restarts (the daemon).
    ``simulation``: an existing one to build on (tests that prepare a world)."""
    if simulation is None and needs_simulation(config):
        simulation = load_entry(SIMULATION)(config, scan_process=scan_process, state_file=state_file)
    if simulation is not None:
        config = simulation.config
    try:
        devices = {role: build_real_device(role, config) if getattr(config, role).driver != "sim"
                   else simulation.device(role) for role in cell_roles(config)}
    except ValueError as e:
        raise CellBuildError(str(e)) from e
    return Cell(**devices, simulation=simulation)
