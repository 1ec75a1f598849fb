"""Simulated twins of every device, all acting on one :class:`SimWorld`.

Each twin implements its Protocol from :mod:`tandemscan.drivers.interfaces`. Motion takes simulated time
(``sim.time_scale`` x the physical duration in wall time; 0 makes it instant). Injected faults come from
``[sim]`` settings: scanner timeouts, an e-stop after a number of chassis moves, an arm servo fault from its n-th
move on and a tracker that stops answering after n frames. Every move, capture and
reading saves the world's state where it has a state file (``sim_drivers.persist``), as a real cell keeps
its robots where they stopped.
"""

from __future__ import annotations

import asyncio
import time

import numpy as np
from tandemscan.drivers.errors import DeviceFault, DeviceTimeout, NotConnected, SafetyStop
from tandemscan.drivers.interfaces import (
    ChassisPose,
    DeviceState,
    DeviceStatus,
    SafetyState,
    ScanFrame,
    TrackerReading,
)
from tandemscan.sim_drivers.persist import keep_world_state
from tandemscan.sim_drivers.scan_process import ScanProcess
from tandemscan.sim_drivers.world import SimWorld

# Time (s) a PhoXi S takes for one capture at full quality (simulated).
_SCAN_TIME_S = 0.5
# Time (s) between two tracker frames (simulated).
_TRACKER_FRAME_S = 0.02


class _SimDevice:
    """Common lifecycle of a twin: a name, a connected flag and a state string."""

    def __init__(self, name: str, world: SimWorld):
        self.name = name
        self.world = world
        self._connected = False
        self._state = DeviceState.DISCONNECTED

    async def connect(self) -> None:
        self._connected = True
        self._state = DeviceState.IDLE

    async def close(self) -> None:
        self._connected = False
        self._state = DeviceState.DISCONNECTED

    async def status(self) -> DeviceStatus:
        return DeviceStatus(self.name, self._connected, self._state, self._detail())

    def _detail(self) -> dict[str, object]:
        return {}

    def _require_connected(self) -> None:
        if not self._connected:
            raise NotConnected(self.name, "not connected")

    def _require_motion_allowed(self) -> None:
        s = self.world.safety
        if s.estop or s.light_curtain_broken:
            raise SafetyStop(self.name, "motion refused: " + ("e-stop" if s.estop else "light curtain broken"))

    async def _elapse(self, seconds: float) -> None:
        await asyncio.sleep(seconds * self.world.config.sim.time_scale)


class SimChassis(_SimDevice):
    """An AGV twin: closed loop on its odometry, lands with slip; the true pose stays in the world."""

    def __init__(self, name: str, world: SimWorld, robot: str):
        super().__init__(name, world)
        self.robot = robot

    @property
    def _truth(self):
        return self.world.chassis[self.name]

    async def move_to(self, target: ChassisPose, timeout_s: float | None = None) -> ChassisPose:
        self._require_connected()
        self._require_motion_allowed()
        cfg = getattr(self.world.config, self.name)  # the chassis' speeds and timeout (ChassisConfig)
        self._state = DeviceState.MOVING
        self.world.motion.start(self.robot)
        try:
            distance, turn = self._truth.apply_move(target, self.world.rng)
            duration = distance / cfg.speed_mm_s + np.degrees(turn) / cfg.turn_rate_deg_s
            limit = cfg.timeout_s if timeout_s is None else timeout_s
            if duration > limit:
                raise DeviceTimeout(self.name, f"move needs {duration:.0f} s, over the {limit:.0f} s timeout")
            await self._elapse(duration)
            n = self.world.config.sim.fault_estop_after_moves
            if n and sum(c.moves for c in self.world.chassis.values()) >= n:
                self.world.safety.estop = True
        finally:
            self.world.motion.stop(self.robot)
            self._state = DeviceState.IDLE
            keep_world_state(self.world)
        return self._truth.odometry

    async def odometry(self) -> ChassisPose:
        self._require_connected()
        return self._truth.odometry

    async def set_odometry(self, pose: ChassisPose) -> None:
        self._require_connected()
        self._truth.odometry = pose
        keep_world_state(self.world)

    async def stop(self) -> None:
        self._state = DeviceState.IDLE

    def _detail(self) -> dict[str, object]:
        o = self._truth.odometry
        return {"x_mm": o.x_mm, "y_mm": o.y_mm, "heading_rad": o.heading_rad, "moves": self._truth.moves}


class SimArm(_SimDevice):
    """A JAKA Zu twin: joint moves within limits at the configured joint speed."""

    def __init__(self, name: str, world: SimWorld):
        super().__init__(name, world)
        self._moves = 0

    async def enable(self) -> None:
        self._require_connected()

    async def move_joints(self, joints_rad: np.ndarray, timeout_s: float | None = None) -> None:
        self._require_connected()
        self._require_motion_allowed()
        self._moves += 1
        n = self.world.config.sim.fault_arm_after_moves
        if n and self._moves >= n:
            raise DeviceFault(self.name, "servo fault on joint 2 (injected fault)")
        self._state = DeviceState.MOVING
        self.world.motion.start(SimWorld.MEASURE_ROBOT)
        try:
            travel = self.world.move_arm(joints_rad)
            await self._elapse(np.degrees(travel) / self.world.config.arm.joint_speed_deg_s)
        finally:
            self.world.motion.stop(SimWorld.MEASURE_ROBOT)
            self._state = DeviceState.IDLE
            keep_world_state(self.world)

    async def joints(self) -> np.ndarray:
        self._require_connected()
        return self.world.joints_rad.copy()

    async def flange_pose(self) -> np.ndarray:
        self._require_connected()
        return self.world.kinematics.forward(self.world.joints_rad)

    async def stop(self) -> None:
        self._state = DeviceState.IDLE

    def _detail(self) -> dict[str, object]:
        return {"joints_deg": np.degrees(self.world.joints_rad).round(3).tolist()}


class SimScanner(_SimDevice):
    """A PhoXi S twin: ray casting on the part mesh, 0.05 mm noise along the ray.

    With ``out_of_process`` the rays are cast in a worker process (:class:`ScanProcess`, started at connect),
    as the daemon needs; otherwise in a thread. Both give the same capture for the same world state."""

    def __init__(self, name: str, world: SimWorld, out_of_process: bool = False):
        super().__init__(name, world)
        self.out_of_process = out_of_process
        self._process: ScanProcess | None = None

    async def connect(self) -> None:
        if self.out_of_process and self._process is None:
            config = self.world.config
            self._process = ScanProcess(config, config.daemon.worker_niceness)
        await super().connect()

    async def close(self) -> None:
        await super().close()
        if self._process is not None:
            process, self._process = self._process, None
            await asyncio.to_thread(process.close)

    async def capture(self, timeout_s: float | None = None) -> ScanFrame:
        self._require_connected()
        n = self.world.config.sim.fault_scanner_timeout_every
        if n and (self.world.captures + 1) % n == 0:
            self.world.captures += 1
            raise DeviceTimeout(self.name, "no frame within the capture timeout (injected fault)")
        self._state = DeviceState.BUSY
        try:
            await self._elapse(_SCAN_TIME_S)
            if self._process is not None:
                self.world.captures += 1
                points, normals = await self._process.scan(self.world.T_F_S(), self.world.rng)
            else:
                points, normals = await asyncio.to_thread(self.world.scan)
        finally:
            self._state = DeviceState.IDLE
            keep_world_state(self.world)
        return ScanFrame(points, normals, None, time.time())


class SimTracker(_SimDevice):
    """A Metronor twin: noisy ``T_C_T`` with field of view, range and occlusion by the part."""

    async def read_pose(self, timeout_s: float | None = None) -> TrackerReading:
        self._require_connected()
        n = self.world.config.sim.fault_tracker_after_frames
        if n and self.world.tracker_frames >= n:
            raise DeviceTimeout(self.name, "no pose within the timeout (injected fault)")
        await self._elapse(_TRACKER_FRAME_S)
        try:
            T_C_T, cov = self.world.measure_target()
        finally:
            keep_world_state(self.world)
        return TrackerReading(T_C_T, cov, time.time(), self.world.tracker_frames)


class SimSafetyIO(_SimDevice):
    """Cell safety I/O twin: reads the world's e-stop and light curtain, drives the target light."""

    async def read(self) -> SafetyState:
        self._require_connected()
        s = self.world.safety
        return SafetyState(s.estop, s.light_curtain_broken, s.target_light_on)

    async def set_target_light(self, on: bool) -> None:
        self._require_connected()
        self.world.safety.target_light_on = on
