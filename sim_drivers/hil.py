"""Hardware-in-the-loop: every protocol emulator a ``driver = "real"`` device needs, backed by one SimWorld.

Started before the real drivers connect (``[hil] enabled = true``): the JAKA controller and the tracker stream on
their configured 127.0.0.1 ports, one chassis per configured CAN channel, the Modbus I/O module, and the fake
harvesters camera; for a plugin's driver, the emulator the plugin registers (group ``tandemscan.emulators``,
:mod:`tandemscan.config.device_registry`). Each emulator moves or reads the world, so a job run through the real
drivers can be scored against the same ground truth as one run on the twins. The world's state is saved whenever an
emulated robot reports a pose at rest other than the one last saved (the end of every move, however short, and where
a stop cut one short) and whenever the tracker's still error is drawn anew, so a restarted daemon finds the robots
where they stopped and the still target read with the error it had, as the twins' cell does (the drivers' odometry
starts afresh, as a real cell's: the resumed job re-localises it, docs/daemon.md).
"""

from __future__ import annotations

import asyncio
import logging
from typing import Protocol

import numpy as np
from tandemscan.config.device_registry import BUILT_IN_DRIVERS, EMULATOR_GROUP, cell_roles, load_registered
from tandemscan.config.models import CellConfig
from tandemscan.drivers.interfaces import ChassisPose
from tandemscan.drivers.tasks import cancel_and_wait
from tandemscan.pipeline.geometry import frames as F
from tandemscan.sim_drivers.emulators.agv_can import ChassisEmulator
from tandemscan.sim_drivers.emulators.jaka import JakaBehaviour, JakaEmulator
from tandemscan.sim_drivers.emulators.safety_modbus import SafetyIoEmulator
from tandemscan.sim_drivers.emulators.tracker import TrackerStreamEmulator
from tandemscan.sim_drivers.fake_harvesters import core as fake_harvesters
from tandemscan.sim_drivers.persist import keep_world_state
from tandemscan.sim_drivers.world import SimWorld

log = logging.getLogger(__name__)


class _Emulator(Protocol):
    async def stop(self) -> None: ...


def start_pose_of(world: SimWorld, role: str) -> ChassisPose:
    """The true floor pose of chassis ``role`` now, as (x, y, heading)."""
    T = world.chassis[role].true_pose
    return ChassisPose(float(T[0, 3]), float(T[1, 3]), float(np.arctan2(T[1, 0], T[0, 0])))


class HilEmulators:
    """``start()`` the emulators for the real devices of ``config``; ``stop()`` them after the drivers closed."""

    def __init__(self, config: CellConfig, world: SimWorld):
        self.config, self.world = config, world
        self.running: dict[str, _Emulator] = {}
        self._sync_task: asyncio.Task | None = None
        self._kept: dict[str, np.ndarray] = {}  # each emulated mover's pose at rest when the world was last saved

    def _real(self, role: str) -> bool:
        return getattr(self.config, role).driver == "real"

    async def start(self) -> None:
        try:
            await self._start_all()
        except BaseException:
            await self.stop()
            raise

    async def _start_all(self) -> None:
        cfg, world, hil = self.config, self.world, self.config.hil
        if self._real("arm"):
            jaka = cfg.arm.jaka
            arm = JakaEmulator(cfg.arm, host=jaka.host, command_port=jaka.command_port, status_port=jaka.status_port,
                               time_scale=hil.arm_time_scale, initial_joints_rad=world.joints_rad,
                               on_joints=self._arm_moved, kinematics=world.kinematics,
                               behaviour=JakaBehaviour(
                                   power_on_delay_s=hil.arm_power_on_delay_s, enable_delay_s=hil.arm_enable_delay_s,
                                   segment_bytes=hil.arm_segment_bytes,
                                   numeric_error_codes=hil.arm_numeric_error_codes,
                                   status_bytes=hil.arm_status_bytes))
            await arm.start()
            self.running["arm"] = arm
        for role in ("measure_chassis", "tracking_chassis"):
            if self._real(role):
                can_cfg = getattr(cfg, role).can
                chassis = ChassisEmulator(getattr(cfg, role), can_cfg.channel, can_cfg.interface,
                                          time_scale=hil.chassis_time_scale, seed=cfg.sim.seed,
                                          start_pose=start_pose_of(world, role), on_pose=self._chassis_mover(role),
                                          driver_state_flags=hil.chassis_driver_state_flags,
                                          odometry_start_counts=hil.chassis_odometry_start_counts,
                                          truth=world.chassis[role])
                await chassis.start()
                self.running[role] = chassis
        if self._real("tracker"):
            stream = cfg.tracker.stream
            tracker = TrackerStreamEmulator(stream, self._measure_target, rate_hz=hil.tracker_rate_hz,
                                            requires_start=hil.tracker_requires_start)
            await tracker.start_tcp(stream.host, stream.port)
            self.running["tracker"] = tracker
        if self._real("safety"):
            safety = SafetyIoEmulator(cfg.safety.modbus, cfg.safety.modbus.host, cfg.safety.modbus.port)
            await safety.start()
            self.running["safety"] = safety
            self._sync_task = asyncio.create_task(self._sync_safety(safety))
        if self._real("scanner"):
            fake_harvesters.CAMERA.reset()
            fake_harvesters.CAMERA.interface = cfg.scanner.phoxi.interface
            fake_harvesters.CAMERA.scene = self._scan_as_buffer
        await self._start_plugins()
        log.info("hil: emulators running for %s", ", ".join(self.running) or "no device")

    async def _start_plugins(self) -> None:
        """The emulator of each plugin's driver: its registered ``start(section, world)``, awaited, gives the
        running emulator (something with ``async stop()``) that serves the section's settings on this world."""
        for role in cell_roles(self.config):
            section = getattr(self.config, role)
            if section.driver not in BUILT_IN_DRIVERS:
                start = load_registered(EMULATOR_GROUP, role, section.driver)
                self.running[role] = await start(section, self.world)

    async def stop(self) -> None:
        await cancel_and_wait(self._sync_task)
        self._sync_task = None
        for emulator in reversed(list(self.running.values())):
            await emulator.stop()
        self.running.clear()

    # ------------------------------------------------------------------ world hooks

    def _arm_moved(self, q_rad: np.ndarray, moving: bool) -> None:
        (self.world.motion.start if moving else self.world.motion.stop)(SimWorld.MEASURE_ROBOT)
        self.world.joints_rad = np.asarray(q_rad, float)
        self._keep_at_rest("arm", self.world.joints_rad, moving)

    def _chassis_mover(self, role: str):
        robot = SimWorld.MEASURE_ROBOT if role == "measure_chassis" else SimWorld.TRACKING_ROBOT

        def moved(pose: ChassisPose, moving: bool) -> None:
            self.world.chassis[role].true_pose = F.planar_pose(pose.x_mm, pose.y_mm, pose.heading_rad)
            (self.world.motion.start if moving else self.world.motion.stop)(robot)
            self._keep_at_rest(role, self.world.chassis[role].true_pose, moving)

        return moved

    def _keep_at_rest(self, mover: str, pose: np.ndarray, moving: bool) -> None:
        """Save the world's state (:func:`~tandemscan.sim_drivers.persist.keep_world_state`) when ``mover`` reports
        a ``pose`` at rest (joints rad, or a chassis' 4x4 mm) other than the one last saved, so that a restarted
        daemon finds the robots where they stopped, as the twins' cell does. Not on the change from moving to rest:
        a move shorter than the emulator's report period is never reported moving, and its end would not be kept."""
        if moving or np.array_equal(self._kept.get(mover), pose):
            return
        self._kept[mover] = np.array(pose, float)
        keep_world_state(self.world)

    def _measure_target(self) -> tuple[np.ndarray, np.ndarray]:
        """The world's target reading for the tracker emulator; the state saved when the reading began a new still
        period with every robot at rest, so that a restarted daemon's tracker reads the still target with the error
        it had (not at every frame of a move)."""
        still = self.world.still_T_C_T
        reading = self.world.measure_target()
        if self.world.still_T_C_T is not still and not self.world.motion.moving:
            keep_world_state(self.world)
        return reading

    def _scan_as_buffer(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The world's scan laid out as a one-row image (the fake camera's buffer shape); an empty scan is one
        invalid (zero) pixel, as a real frame where nothing was in range."""
        points, normals = self.world.scan()
        if len(points) == 0:
            points, normals = np.zeros((1, 3)), np.zeros((1, 3))
        n = len(points)
        return (points.reshape(1, n, 3).astype(np.float32), normals.reshape(1, n, 3).astype(np.float32),
                np.ones((1, n), np.float32))

    async def _sync_safety(self, safety: SafetyIoEmulator) -> None:
        """Mirror the world's e-stop and light curtain onto the inputs, and the target-light coil back."""
        truth, mb = self.world.safety, self.config.safety.modbus
        inputs = None  # the (e-stop, light curtain) last written: the module's inputs change only when the world's do
        while True:
            if inputs != (truth.estop, truth.light_curtain_broken):
                inputs = (truth.estop, truth.light_curtain_broken)
                await safety.press_estop(inputs[0])
                await safety.break_light_curtain(inputs[1])
            truth.target_light_on = await safety.coil(mb.target_light_coil)
            await asyncio.sleep(self.config.safety.poll_period_s / 2)
