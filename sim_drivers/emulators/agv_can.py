"""CAN chassis emulator: an AgileX-Scout-style (protocol v2) chassis on a python-can bus.

It boots in standby, takes motion commands only in CAN mode, stops by itself when commands stop for
``watchdog_s`` (wall time), and every ``period_s`` sends system status, motion state and wheel odometry
(motor low-rate frames every fifth period). The body moves in simulated time (``time_scale`` wall seconds
per simulated second) with wheel slip: the true pose (``true_pose``, reported through ``on_pose``) drifts
away from what the wheel odometry says. Faults are injected through :class:`ChassisFaults`.

As a real chassis (ugv_sdk protocol v2), every motor driver may report state bits that are not faults in normal
running (``driver_state_flags``, e.g. 0x40 "driver enabled"), and the odometry frame carries raw counts of
``odometry_mm_per_count`` mm, int32 counters that wrap (``odometry_start_counts`` starts them anywhere, e.g. near
the limit). Error 0x0004 (RC lost) stops the chassis only while the RC has control, not in CAN mode.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import can
import numpy as np
from tandemscan.config.models import ChassisConfig
from tandemscan.drivers.can_link import CanFrameError, CanLink, load_dbc
from tandemscan.drivers.interfaces import ChassisPose
from tandemscan.drivers.tasks import cancel_and_wait
from tandemscan.sim_drivers.config import ChassisSlipConfig
from tandemscan.sim_drivers.world import ChassisTruth

log = logging.getLogger(__name__)

MAX_LINEAR_MM_S = 1500.0
MAX_ANGULAR_RAD_S = 2.5
RC_LOST = 0x0004
NOT_STOPPING_ERRORS = 0x0002 | RC_LOST  # battery warning; RC lost outside RC mode (the transmitter may be off)


def int32_wrapped(value: int) -> int:
    """``value`` as an int32 counter shows it (wrapped modulo 2^32 into [-2^31, 2^31))."""
    return (value + (1 << 31)) % (1 << 32) - (1 << 31)


@dataclass
class ChassisFaults:
    """Fault injection; flags may change while the emulator runs."""

    drop_feedback_fraction: float = 0.0  # this fraction of outgoing frames is lost
    ignore_commands: bool = False  # the chassis stops hearing motion commands (its watchdog then stops it)
    silent: bool = False  # the chassis sends nothing (link loss seen from the host)
    estop: bool = False  # vehicle state e-stop, velocity zero
    error_code: int = 0  # SystemStatus.ErrorCode bits
    driver_state: int = 0  # motor 1 DriverState bits
    rc_override: bool = False  # the RC transmitter takes control
    bad_dlc_next: bool = False  # the next system status frame is sent with DLC 3


class SkidSteerBody:
    """Planar skid-steer motion with slip, in simulated seconds; swap for a richer model.

    Distance and turn slip factors (1-sigma ``slip_distance_fraction``) are drawn each time the body starts
    from standstill; a heading drift per distance travelled has 1-sigma ``slip_heading_deg`` per metre. The
    wheel encoders see the commanded motion scaled by a fixed odometry error (``odometry_drift_fraction``).
    """

    def __init__(self, slip: ChassisSlipConfig, track_mm: float, rng: np.random.Generator,
                 odometry_scale: float | None = None):
        """``odometry_scale``: the encoders' fixed scale error (default: drawn from ``rng``)."""
        self.cfg, self.track_mm, self.rng = slip, track_mm, rng
        self.x_mm = self.y_mm = self.heading_rad = 0.0
        self.left_mm = self.right_mm = 0.0
        self.odometry_scale = (1.0 + rng.normal(0.0, slip.odometry_drift_fraction) if odometry_scale is None
                               else odometry_scale)
        self._moving = False
        self._slip = (1.0, 1.0, 0.0)

    def step(self, v_mm_s: float, w_rad_s: float, dt_s: float) -> None:
        moving = v_mm_s != 0.0 or w_rad_s != 0.0
        if moving and not self._moving:
            s = self.cfg.slip_distance_fraction
            self._slip = (1 + self.rng.normal(0, s), 1 + self.rng.normal(0, s),
                          self.rng.normal(0, math.radians(self.cfg.slip_heading_deg)) / 1000.0)
        self._moving = moving
        ks, kw, drift_per_mm = self._slip
        ds, dth = v_mm_s * ks * dt_s, w_rad_s * kw * dt_s + abs(v_mm_s * dt_s) * drift_per_mm
        mid = self.heading_rad + dth / 2
        self.x_mm += ds * math.cos(mid)
        self.y_mm += ds * math.sin(mid)
        self.heading_rad = (self.heading_rad + dth + math.pi) % (2 * math.pi) - math.pi
        wheel_ds, wheel_dth = v_mm_s * dt_s * self.odometry_scale, w_rad_s * dt_s * self.odometry_scale
        self.left_mm += wheel_ds - wheel_dth * self.track_mm / 2
        self.right_mm += wheel_ds + wheel_dth * self.track_mm / 2


class ChassisEmulator:
    """A chassis on ``interface:channel``; ``start()`` / ``stop()`` from the running loop."""

    def __init__(
        self,
        config: ChassisConfig,
        channel: str,
        interface: str = "virtual",
        period_s: float = 0.02,
        watchdog_s: float = 0.5,
        time_scale: float = 1.0,
        seed: int = 0,
        start_pose: ChassisPose | None = None,
        on_pose: Callable[[ChassisPose, bool], None] | None = None,
        driver_state_flags: int = 0,
        odometry_mm_per_count: float = 1.0,
        slip: ChassisSlipConfig | None = None,
        standstill_speed_mm_s: float = 0.0,
        truth: ChassisTruth | None = None,
        reports_host_timeout: bool = False,
        odometry_start_counts: int = 0,
    ):
        """``on_pose(true pose, moving)`` is called every period (e.g. to move the simulated world's chassis);
        ``driver_state_flags``: DriverState bits every motor reports in normal running (0x40, 0x80); ``slip``: how
        the body misses its commands (``[sim.<role>_slip]``; the default when not given);
        ``standstill_speed_mm_s``: the linear speed the motion state reports while the body stands still (a
        real chassis's speed comes from its encoders and may show a count of noise there; 0: exactly zero);
        ``truth``: the simulated world's chassis, whose slip model, slip stream and odometry scale error the body
        takes (the hardware-in-the-loop cell: the world keeps them across a restart) in place of ``slip`` and draws
        from ``seed``; ``reports_host_timeout``: the system status reports error 0x0200 (host communication, vehicle
        state "exception") while no motion command came for ``watchdog_s``, from boot until the first one too;
        ``odometry_start_counts``: both odometry counters' value at boot (raw counts; near 2^31 they wrap soon)."""
        self.driver_state_flags = driver_state_flags
        self.reports_host_timeout = reports_host_timeout
        self.standstill_speed_mm_s = standstill_speed_mm_s
        self.odometry_mm_per_count = odometry_mm_per_count
        self.odometry_start_counts = odometry_start_counts
        self.config = config
        self.faults = ChassisFaults()
        self.period_s, self.watchdog_s, self.time_scale = period_s, watchdog_s, time_scale
        self.on_pose = on_pose
        self.rng = np.random.default_rng(seed)  # frame drops; the body's slip draws too unless ``truth`` is given
        if truth is None:
            self.body = SkidSteerBody(slip or ChassisSlipConfig(), config.can.odometry_track_mm, self.rng)
        else:
            self.body = SkidSteerBody(truth.cfg, config.can.odometry_track_mm, truth.slip_rng,
                                      odometry_scale=1.0 + truth.scale_bias)
        if start_pose is not None:
            p = start_pose
            self.body.x_mm, self.body.y_mm, self.body.heading_rad = p.x_mm, p.y_mm, p.heading_rad
        self.mode = 0
        self.command = (0.0, 0.0)
        self.velocity = (0.0, 0.0)  # what the chassis actually does (mm/s, rad/s)
        self.watchdog_tripped = False
        self.commands_received = 0
        self._last_command_t = -math.inf
        self._link = CanLink(interface, channel, config.can.bitrate, load_dbc(config.can.dbc))
        self._tasks: list[asyncio.Task] = []
        self._counter = 0

    @property
    def true_pose(self) -> ChassisPose:
        return ChassisPose(self.body.x_mm, self.body.y_mm, self.body.heading_rad)

    async def start(self) -> None:
        self._link.open()
        self._tasks = [asyncio.create_task(self._receive()), asyncio.create_task(self._run())]

    async def stop(self) -> None:
        for t in self._tasks:
            await cancel_and_wait(t)
        self._tasks = []
        await self._link.close()

    async def _receive(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            try:
                name, sig, _ = await self._link.recv()
            except CanFrameError as e:
                log.warning("chassis emulator: %s", e)
                continue
            if name == "ControlModeSet":
                self.mode = int(sig["ControlMode"])
            elif name == "MotionCommand" and not self.faults.ignore_commands:
                self.commands_received += 1
                self.command = (float(sig["LinearVelocity"]), float(sig["AngularVelocity"]))
                self._last_command_t = loop.time()
            elif name == "ErrorClear":
                self.faults.error_code = 0
                self.faults.driver_state &= 0x01  # the supply voltage stays low: a condition, not a latched error

    def _effective_velocity(self, now: float) -> tuple[float, float]:
        self.watchdog_tripped = now - self._last_command_t > self.watchdog_s
        mode = 3 if self.faults.rc_override else self.mode
        if mode != 1 or self.faults.estop or self.faults.error_code & ~NOT_STOPPING_ERRORS \
                or self.faults.driver_state & ~0x01:
            return 0.0, 0.0
        if self.watchdog_tripped:
            return 0.0, 0.0
        v, w = self.command
        return (min(max(v, -MAX_LINEAR_MM_S), MAX_LINEAR_MM_S), min(max(w, -MAX_ANGULAR_RAD_S), MAX_ANGULAR_RAD_S))

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        last = loop.time()
        while True:
            await asyncio.sleep(self.period_s)
            now = loop.time()
            dt_sim = (now - last) / self.time_scale if self.time_scale > 0 else 0.0
            last = now
            self.body.step(*self.velocity, dt_sim)  # the velocity held over the period that just ended
            self.velocity = self._effective_velocity(now)
            if self.on_pose is not None:
                self.on_pose(self.true_pose, self.velocity != (0.0, 0.0))
            if not self.faults.silent:
                with contextlib.suppress(can.CanError):
                    self._send_feedback()

    def _send_feedback(self) -> None:
        self._counter = (self._counter + 1) % 256
        if self.faults.bad_dlc_next:
            self.faults.bad_dlc_next = False
            self._link.send_raw(self._link.db.get_message_by_name("SystemStatus").frame_id, b"\x00\x01\x00")
        else:
            code = self.faults.error_code | (0x0200 if self.reports_host_timeout and self.watchdog_tripped else 0)
            state = 1 if self.faults.estop else (2 if code & ~NOT_STOPPING_ERRORS else 0)
            mode = 3 if self.faults.rc_override else self.mode
            self._maybe_send("SystemStatus", VehicleState=state, ControlMode=mode, BatteryVoltage=25.2,
                             ErrorCode=code, Counter=self._counter)
        v, w = self.velocity if self.velocity != (0.0, 0.0) else (self.standstill_speed_mm_s, 0.0)
        self._maybe_send("MotionState", LinearVelocity=round(v), AngularVelocity=round(w, 3),
                         LateralVelocity=0, SteeringAngle=0)
        self._maybe_send("Odometry", LeftWheelOdometry=self._odometry_counts(self.body.left_mm),
                         RightWheelOdometry=self._odometry_counts(self.body.right_mm))
        if self._counter % 5 == 0:
            for i in range(1, 5):
                faults = self.faults.driver_state if i == 1 else 0
                volts = 21.5 if faults & 0x01 else 25.0  # 0x01: supply voltage low, a warning; it drives on
                self._maybe_send(f"MotorLowRate{i}", DriverVoltage=volts, DriverTemperature=35, MotorTemperature=30,
                                 DriverState=faults | self.driver_state_flags)

    def _odometry_counts(self, wheel_mm: float) -> int:
        return int32_wrapped(self.odometry_start_counts + round(wheel_mm / self.odometry_mm_per_count))

    def _maybe_send(self, name: str, **signals: float) -> None:
        if self.faults.drop_feedback_fraction and self.rng.random() < self.faults.drop_feedback_fraction:
            return
        self._link.send(name, **signals)
