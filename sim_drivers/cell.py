"""The simulated cell behind the twins and the hardware-in-the-loop emulators, as the product's cell layer sees it.

:class:`Simulation` implements :class:`tandemscan.daemon.cell.devices.CellSimulation` and is loaded lazily through the
device registry (:data:`tandemscan.drivers.factory.SIMULATION`). It owns the :class:`SimWorld`, builds each
role's twin (the registry's ``"sim"`` class), runs the emulators for the real drivers with ``[hil] enabled``,
keeps the world's state in ``state_file`` (the twins save it as they move, scan and read; it is restored when
the session starts, as a real cell finds its robots where they stopped) and hands out the ground-truth
observers (:mod:`tandemscan.sim_drivers.truth_observer`). A hardware-in-the-loop cell whose every device is a real
driver is a real cell to the product: its jobs get no observer, and it has no true mounts to survey (the world
still moves under the emulators, and a calibration still finds its plate there).

The product never reads the simulated cell's true mounts. A benchmark or test that measures the correction
apart from the calibration's error hands its job a calibration file of them (:func:`with_surveyed_mounts`), as
an exact survey of the cell would give it.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from functools import partial
from pathlib import Path

import numpy as np
from tandemscan.config import load_config
from tandemscan.config.models import CellConfig
from tandemscan.drivers.factory import ROLES, device_class
from tandemscan.drivers.interfaces import Device
from tandemscan.sim_drivers.hil import HilEmulators
from tandemscan.sim_drivers.persist import keep_world_state, load_world_state
from tandemscan.sim_drivers.truth_observer import CalibrationTruth, TruthObserver
from tandemscan.sim_drivers.world import SimWorld

log = logging.getLogger(__name__)

#: 1-sigma per axis (mm, rad) that the survey's calibration file states for T_T_S: exact (0.1 um, 0.1 urad), so
#: that a job's correction keeps the surveyed mount and only stays numerically regular
SURVEY_SIGMA_MM, SURVEY_SIGMA_RAD = 1e-4, 1e-7


class Simulation:
    """One simulated world and what hangs off it; ``world`` may be given (tests that prepare one)."""

    def __init__(self, config: CellConfig, *, scan_process: bool = False, state_file: Path | None = None,
                 world: SimWorld | None = None):
        self.world = world if world is not None else SimWorld(config)
        self.world.state_file = state_file
        real = {role for role in ROLES if getattr(config, role).driver != "sim"}  # a vendor's, built-in or a plugin's
        self.config = _odometry_from_sim_start(config) if config.hil.enabled and real else config
        self.scan_process = scan_process
        self.scores = len(real) < len(ROLES)  # some device is a twin: jobs are scored against the truth
        self.emulators = HilEmulators(self.config, self.world) if config.hil.enabled else None

    def device(self, role: str) -> Device:
        """The twin of ``role`` on this world (the registry's ``"sim"`` class)."""
        options = {"measure_chassis": {"robot": SimWorld.MEASURE_ROBOT},
                   "tracking_chassis": {"robot": SimWorld.TRACKING_ROBOT},
                   "scanner": {"out_of_process": self.scan_process}}.get(role, {})
        return device_class(role, "sim")(role, self.world, **options)

    async def start(self) -> None:
        """Restore the saved world state (if any), then start the emulators."""
        path = self.world.state_file
        if path is not None and load_world_state(self.world, path):
            log.info("simulated world restored from %s", path)
        if self.emulators is not None:
            await self.emulators.start()

    async def stop(self) -> None:
        if self.emulators is not None:
            await self.emulators.stop()

    def job_observer(self, job_key: str, resumed: bool) -> TruthObserver | None:
        if not self.scores:
            return None
        return TruthObserver(self.world, job_key, resumed, partial(keep_world_state, self.world))

    def calibration_observer(self) -> CalibrationTruth:
        return CalibrationTruth(self.world, self.scores)

    def write_survey(self, path: Path) -> Path:
        """Write the cell's true mounts (mm), as an exact survey gives them, to ``path`` as a calibration file
        (``Installation.load`` reads it; its ``T_T_S_covariance`` is :data:`SURVEY_SIGMA_MM` /
        :data:`SURVEY_SIGMA_RAD`). ValueError on a cell whose every device is a real driver: it has no truth."""
        if not self.scores:
            raise ValueError("a cell of real drivers has no simulated truth to survey")
        covariance = np.diag([SURVEY_SIGMA_MM**2] * 3 + [SURVEY_SIGMA_RAD**2] * 3)
        survey = {**dataclasses.replace(self.world.truth, T_T_S_covariance=covariance).to_json(),
                  "sources": {"all": "simulated cell's true mounts (exact survey)"}}
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(survey, indent=1), encoding="utf-8")
        return path


def with_surveyed_mounts(config: CellConfig, simulation: Simulation | None, folder: Path) -> CellConfig:
    """``config`` with its jobs stitching with ``simulation``'s true mounts: written as a calibration file
    (:meth:`Simulation.write_survey`) into ``folder``, and ``[job] installation_source = "calibration"`` on it.
    For benchmarks and tests that measure the correction apart from the calibration's error. ValueError where
    there is no simulated cell (``simulation`` None: a cell of real drivers)."""
    if simulation is None:
        raise ValueError("a cell of real drivers has no simulated truth to survey")
    path = simulation.write_survey(Path(folder) / "surveyed_mounts.json")
    job = config.job.model_copy(update={"installation_source": "calibration", "calibration_file": path})
    return config.model_copy(update={"job": job})


def with_surveyed_mounts_toml(toml: Path) -> Path:
    """The same for a cell configuration file that a child process (``tandemscan serve``) reads: the simulated
    cell it configures is surveyed into ``surveyed_mounts.json`` beside it, and a ``[job]`` table naming that
    file is appended (``toml`` must not have one). Returns ``toml``."""
    toml = Path(toml)
    survey = Simulation(load_config(toml)).write_survey(toml.parent / "surveyed_mounts.json")
    with toml.open("a", encoding="utf-8") as f:
        f.write(f'\n[job]\ninstallation_source = "calibration"\ncalibration_file = "{survey}"\n')
    return toml


def _odometry_from_sim_start(config: CellConfig) -> CellConfig:
    """In a hardware-in-the-loop cell the chassis odometry starts at the simulated start poses, as the twins'."""
    update = {}
    for role, start in (("measure_chassis", config.sim.measure_start), ("tracking_chassis", config.sim.tracking_start)):
        section = getattr(config, role)
        if section.driver == "real":  # the built-in CAN chassis; a plugin's starts where its own settings say
            can = section.can.model_copy(update={"odometry_start_x_mm": start.x_mm, "odometry_start_y_mm": start.y_mm,
                                                 "odometry_start_heading_deg": start.heading_deg})
            update[role] = section.model_copy(update={"can": can})
    return config.model_copy(update=update)
