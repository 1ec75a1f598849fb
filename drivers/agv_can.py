"""AGV chassis over CAN (AgileX-Scout-style protocol v2; frames from the DBC in ``ChassisCanConfig.dbc``).

The driver puts the chassis in CAN command mode, sends the motion command every ``command_period_s`` (the
chassis stops by itself after 500 ms without one), integrates the wheel odometry into a pose in its odometry
frame (mm, rad) and closes the loop on it in :meth:`AgvCanChassis.move_to`. Every fault (e-stop, error bits,
motor-driver state, RC override, malformed frame, silent bus) zeroes the velocity set-point at once and is
raised as a typed error naming the chassis. Connecting is single-flight (one lock over connect and close), and the
background tasks never end with an exception: a lost link is latched as a fault for the supervisor, which reconnects.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import math

import can
from tandemscan.config.models import ChassisConfig
from tandemscan.drivers.can_link import CanFrameError, CanLink, load_dbc
from tandemscan.drivers.errors import DeviceError, DeviceFault, DeviceTimeout, NotConnected, SafetyStop
from tandemscan.drivers.interfaces import ChassisPose, DeviceState, DeviceStatus
from tandemscan.drivers.tasks import cancel_and_wait

log = logging.getLogger(__name__)

# ugv_sdk protocol v2: 0 standby (RC on some firmware), 1 CAN, 2 UART; 3 RC as this DBC's chassis reports it
CONTROL_MODES = {0: "standby", 1: "CAN", 2: "UART", 3: "RC"}
MODE_CAN = 1
MODE_RC = 3
# SystemStatus.ErrorCode bits (generic; vary per model). Warnings do not stop a move.
ERROR_BITS = {
    0x0001: "battery fault", 0x0008: "motor 1 communication",
    0x0010: "motor 2 communication", 0x0020: "motor 3 communication", 0x0040: "motor 4 communication",
    0x0100: "motor driver", 0x0200: "host communication",
}
WARNING_BITS = {0x0002: "battery warning"}
# RC lost: the RC transmitter is off or out of range. A fault only while the RC has control (mode RC); in any other
# mode (CAN above all) the transmitter may simply be off: a warning.
RC_LOST = 0x0004
RC_LOST_NAME = "RC signal lost"
# The 0x311 wheel odometry: int32 counters that wrap; a delta is taken modulo 2^32, signed.
ODOMETRY_COUNTER_MODULUS = 1 << 32
# Host communication: the chassis has not heard a motion command (its 500 ms watchdog). True from its boot until our
# first command arrives: a fault only once a status frame without it showed that the chassis hears us.
HOST_COMMUNICATION = 0x0200
# Motor driver state (0x261-0x264, ugv_sdk DRIVER_STATE_*_MASK): bits 0x02-0x20 are faults; 0x01 (supply
# voltage low) is a warning, as the system status's battery warning is: the bus voltage dips under
# acceleration on a part-charged battery, and a driver that really drops out reports its fault or stops the
# chassis; 0x40 and 0x80 report the driver enabled and reset (normal running shows 0x40), never a fault.
DRIVER_STATE_BITS = {
    0x02: "motor overheat", 0x04: "overload", 0x08: "driver overheat", 0x10: "sensor fault", 0x20: "driver fault",
}
DRIVER_WARNING_BITS = {0x01: "supply voltage low"}
DRIVER_FAULT_MASK = sum(DRIVER_STATE_BITS)
_MIN_LINEAR_MM_S = 10.0
_MIN_ANGULAR_RAD_S = 0.01
_TURN_IN_PLACE_RAD = math.radians(15.0)


def wrap_angle(a: float) -> float:
    """``a`` wrapped to [-pi, pi)."""
    return (a + math.pi) % (2 * math.pi) - math.pi


def bit_names(value: int, table: dict[int, str]) -> list[str]:
    return [name for bit, name in table.items() if value & bit]


def counter_delta(new: int, old: int, modulus: int = ODOMETRY_COUNTER_MODULUS) -> int:
    """``new - old`` of a signed counter that wraps at ``modulus`` (the shorter way round: in [-modulus/2,
    modulus/2))."""
    half = modulus // 2
    return (new - old + half) % modulus - half


class AgvCanChassis:
    """The :class:`~tandemscan.drivers.interfaces.Chassis` on a CAN bus (settings in ``ChassisConfig.can``)."""

    def __init__(self, config: ChassisConfig, name: str = "chassis"):
        self.name = name
        self._cfg = config
        self._can = config.can
        self._db = load_dbc(config.can.dbc)
        self._link: CanLink | None = None
        self._tasks: list[asyncio.Task] = []
        self._setpoint = (0.0, 0.0)  # linear mm/s, angular rad/s
        # the odometry frame is F: it starts at the surveyed start pose and is kept across reconnects
        self._pose = ChassisPose(config.can.odometry_start_x_mm, config.can.odometry_start_y_mm,
                                 math.radians(config.can.odometry_start_heading_deg))
        self._wheels: tuple[int, int] | None = None  # last wheel odometry (raw counts), None until the first frame
        self._system: dict[str, float] = {}
        self._motion: dict[str, float] = {}
        self._last_status_t = 0.0
        self._fault: DeviceError | None = None
        self._commanding = False  # True once the chassis took CAN mode: leaving it is then a fault
        self._heard = False  # True once a status frame showed no host-communication error since connect
        self._warnings: dict[str, str] = {}  # what warns now, by source (the system status, each motor)
        self.last_residual_mm: float | None = None  # distance from the target (odometry) after the last move
        self._feedback = asyncio.Event()
        self._connection = asyncio.Lock()  # one connect or close at a time: each owns the link and tasks it makes
        self._links_opened = 0  # a move ends when the link it started on is closed (a reconnect under it)
        self.command_times: collections.deque[float] = collections.deque(maxlen=2000)  # loop time of each 0x111

    # ------------------------------------------------------------------ lifecycle

    async def connect(self) -> None:
        """Open the bus, switch the chassis to CAN command mode and start the command heartbeat. A connect or close
        called while another runs waits for it, then does its own (a reconnect never overlaps a connect)."""
        async with self._connection:
            await self._connect()

    async def close(self) -> None:
        """Zero the velocity, stop the heartbeat and release the bus; safe to call twice."""
        async with self._connection:
            await self._disconnect()

    async def _connect(self) -> None:
        await self._disconnect()
        link = CanLink(self._can.interface, self._can.channel, self._can.bitrate, self._db)
        try:
            link.open()
        except (can.CanError, OSError, ValueError) as e:
            raise NotConnected(self.name, f"cannot open CAN {self._can.interface}:{self._can.channel}: {e}") from e
        self._link, self._wheels, self._fault, self._system, self._warnings = link, None, None, {}, {}
        self._links_opened += 1
        self._heard = False
        self._last_status_t = asyncio.get_running_loop().time()
        self._tasks = [asyncio.create_task(self._receive(link), name=f"{self.name}-rx")]
        try:
            await self._enter_can_mode()
        except BaseException as e:
            await self._disconnect()
            if isinstance(e, DeviceError):
                self._fault = e  # why the link is down, for the verbs called until the next connect
            raise
        self._commanding = True
        self._tasks.append(asyncio.create_task(self._command_loop(link), name=f"{self.name}-tx"))
        log.info("%s: CAN command mode on %s", self.name, self._can.channel)

    async def _disconnect(self) -> None:
        tasks, self._tasks = self._tasks, []
        for t in tasks:
            await cancel_and_wait(t)
        link, self._link = self._link, None
        self._setpoint, self._commanding = (0.0, 0.0), False
        if link is not None:
            with contextlib.suppress(can.CanError, CanFrameError):
                link.send("MotionCommand", LinearVelocity=0, AngularVelocity=0, LateralVelocity=0, SteeringAngle=0)
            await link.close()
        self._wake()  # a move waiting for feedback ends now

    async def status(self) -> DeviceStatus:
        """Disconnected until a connect has the chassis in CAN mode (while one is under way too)."""
        if self._link is None or not self._commanding:
            return DeviceStatus(self.name, False, DeviceState.DISCONNECTED)
        if isinstance(self._fault, SafetyStop):
            state = DeviceState.STOPPED
        elif self._fault is not None:
            state = DeviceState.FAULT
        else:
            state = DeviceState.IDLE if self._at_rest() else DeviceState.MOVING
        detail = {
            "pose": self._pose, "battery_V": self._system.get("BatteryVoltage"),
            "error_code": self._system.get("ErrorCode"), "control_mode": self._system.get("ControlMode"),
            "fault": str(self._fault) if self._fault else None, "last_residual_mm": self.last_residual_mm,
            "warnings": sorted(self._warnings.values()),
        }
        return DeviceStatus(self.name, True, state, detail)

    # ------------------------------------------------------------------ verbs

    async def odometry(self) -> ChassisPose:
        """The pose integrated from wheel odometry (mm, rad) in the odometry frame."""
        self._require_link()
        return self._pose

    async def set_odometry(self, pose: ChassisPose) -> None:
        """Integrate the wheel odometry on from ``pose`` (mm, rad): a new driver starts at ``[can] odometry_start_*``,
        so a restarted daemon re-localises it where the journal left the chassis."""
        self._require_link()
        log.info("%s: odometry re-localised from %s to %s", self.name, self._pose, pose)
        self._pose = pose

    async def stop(self) -> None:
        """Zero the velocity now (not at the next period) and abort a running :meth:`move_to`."""
        self._latch(SafetyStop(self.name, "stop requested"))

    async def clear_errors(self) -> None:
        """Ask the chassis to clear its latched errors (0x441) and forget the driver's latched fault."""
        self._require_link().send("ErrorClear", ClearCode=0)
        self._fault = None

    async def move_to(self, target: ChassisPose, timeout_s: float | None = None) -> ChassisPose:
        """Drive to ``target`` closed-loop on odometry: turn, drive (forwards or backwards), creep along the
        heading until the target is reached or passed (so the residual is centred, not at the tolerance's
        edge), turn to the heading. The residual distance is kept in ``last_residual_mm`` and logged."""
        self._require_link()
        link_id = self._links_opened
        loop = asyncio.get_running_loop()
        timeout = self._cfg.timeout_s if timeout_s is None else timeout_s
        deadline = loop.time() + timeout
        self._fault = None
        await self._next_feedback(min(timeout, self._can.feedback_timeout_s))  # re-latches a standing fault
        positioning = True
        creep_direction = 0.0  # sign of the last final-approach command; 0 before the final approach
        tol = self._can.position_tolerance_mm
        try:
            while True:
                self._raise_if_interrupted(link_id)
                pose = self._pose
                dx, dy = target.x_mm - pose.x_mm, target.y_mm - pose.y_mm
                dist = math.hypot(dx, dy)
                along = dx * math.cos(pose.heading_rad) + dy * math.sin(pose.heading_rad)
                if positioning and dist <= tol and (abs(along) <= self._can.approach_deadband_mm
                                                    or along * creep_direction < 0):
                    positioning, creep_direction = False, 0.0  # on the target, or just past it
                    self._zero_now()  # now, not at the next heartbeat: no creeping on while the turn starts
                elif not positioning and dist > 2 * tol:
                    positioning = True
                if positioning and dist > tol:
                    self._setpoint = self._drive_command(dist, math.atan2(dy, dx) - pose.heading_rad)
                elif positioning:
                    creep_direction = math.copysign(1.0, along)
                    self._setpoint = (creep_direction * self._creep_speed(abs(along)), 0.0)
                else:
                    err = wrap_angle(target.heading_rad - pose.heading_rad)
                    if abs(err) <= math.radians(self._can.heading_tolerance_deg):
                        rest = await self._come_to_rest(link_id)
                        if self._arrived(rest, target):
                            self.last_residual_mm = math.hypot(target.x_mm - rest.x_mm, target.y_mm - rest.y_mm)
                            log.info("%s: at %s, %.2f mm from the target", self.name, rest, self.last_residual_mm)
                            return rest
                        positioning = True  # drifted out while stopping: approach again
                    self._setpoint = (0.0, self._turn_rate(err))
                if loop.time() > deadline:
                    raise DeviceTimeout(self.name, f"move to {target} not finished within {timeout} s (at {pose})")
                await self._next_feedback(self._can.feedback_timeout_s)
        except BaseException:
            self._zero_now()
            raise

    def _arrived(self, pose: ChassisPose, target: ChassisPose) -> bool:
        return (math.hypot(target.x_mm - pose.x_mm, target.y_mm - pose.y_mm) <= self._can.position_tolerance_mm
                and abs(wrap_angle(target.heading_rad - pose.heading_rad))
                <= math.radians(self._can.heading_tolerance_deg))

    def _at_rest(self) -> bool:
        """Whether the last motion state reports standstill: both speeds within ``standstill_mm_s`` /
        ``standstill_deg_s`` of zero (a chassis reports its encoders' speed, which may show a count of noise at
        rest; none received yet counts as at rest)."""
        return (abs(self._motion.get("LinearVelocity", 0.0)) <= self._can.standstill_mm_s
                and abs(self._motion.get("AngularVelocity", 0.0)) <= math.radians(self._can.standstill_deg_s))

    def _raise_if_interrupted(self, link_id: int) -> None:
        """Raise the latched fault, or NotConnected when link ``link_id`` (the move's) was closed since."""
        if self._fault is not None:
            raise self._fault
        if self._link is None or self._links_opened != link_id:
            raise NotConnected(self.name, "the link was closed during the move")

    async def _come_to_rest(self, link_id: int) -> ChassisPose:
        """Zero the set-point now and wait until the chassis reports standstill; the pose at rest."""
        self._zero_now()
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self._can.feedback_timeout_s
        while not self._at_rest():
            self._raise_if_interrupted(link_id)
            if loop.time() > deadline:
                raise DeviceTimeout(self.name, f"chassis still moving {self._can.feedback_timeout_s} s after stop")
            await self._next_feedback(self._can.feedback_timeout_s)
        return self._pose

    # ------------------------------------------------------------------ control law

    def _turn_rate(self, err_rad: float) -> float:
        w_max = math.radians(self._cfg.turn_rate_deg_s)
        w = min(max(self._can.gain_angular_per_s * err_rad, -w_max), w_max)
        return math.copysign(max(abs(w), _MIN_ANGULAR_RAD_S), err_rad)

    def _creep_speed(self, along_mm: float) -> float:
        """Final-approach speed (mm/s) ``along_mm`` short of the target: proportional, at least the least speed."""
        return min(max(self._can.gain_linear_per_s * along_mm, _MIN_LINEAR_MM_S), self._cfg.speed_mm_s)

    def _drive_command(self, dist_mm: float, bearing_rad: float) -> tuple[float, float]:
        """(linear mm/s, angular rad/s) towards a point ``dist_mm`` away at ``bearing_rad`` from the heading."""
        direction = 1.0
        err = wrap_angle(bearing_rad)
        if abs(err) > math.pi / 2:  # behind: reverse instead of turning around
            direction, err = -1.0, wrap_angle(err - math.pi)
        w = self._turn_rate(err) if abs(err) > 1e-4 else 0.0
        if abs(err) > _TURN_IN_PLACE_RAD:
            return 0.0, w
        return direction * self._creep_speed(dist_mm) * math.cos(err), w

    # ------------------------------------------------------------------ bus side

    def _require_link(self) -> CanLink:
        """The open link; without one, the fault that brought it down (a silent chassis stays a timeout) or
        :class:`NotConnected`."""
        if self._link is None:
            raise self._fault if self._fault is not None else NotConnected(self.name, "not connected")
        return self._link

    async def _enter_can_mode(self) -> None:
        """Send the control-mode frame until a status frame reports CAN mode."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self._can.feedback_timeout_s
        while self._system.get("ControlMode") != MODE_CAN or self._fault is not None:
            if isinstance(self._fault, (SafetyStop, DeviceFault)):
                raise self._fault
            self._require_link().send("ControlModeSet", ControlMode=MODE_CAN)
            if loop.time() > deadline:
                mode = self._system.get("ControlMode")
                seen = f"mode {CONTROL_MODES.get(int(mode), mode)}" if mode is not None else "no status frame"
                raise DeviceTimeout(self.name, f"chassis did not enter CAN mode within "
                                               f"{self._can.feedback_timeout_s} s ({seen})")
            self._fault = None
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(0.1):
                    await self._feedback.wait()

    async def _next_feedback(self, timeout_s: float) -> None:
        try:
            async with asyncio.timeout(timeout_s):
                await self._feedback.wait()
        except TimeoutError:
            self._latch(DeviceTimeout(self.name, f"no feedback from the chassis for {timeout_s} s"))

    def _zero_now(self) -> None:
        self._setpoint = (0.0, 0.0)
        if self._link is not None:
            with contextlib.suppress(can.CanError, CanFrameError):
                self._send_setpoint(self._link)

    def _latch(self, error: DeviceError) -> None:
        """Record the first fault, zero the velocity at once and wake a waiting move."""
        if self._fault is None:
            log.warning("%s", error)
            self._fault = error
        self._zero_now()
        self._wake()

    def _wake(self) -> None:
        self._feedback.set()
        self._feedback = asyncio.Event()

    def _send_setpoint(self, link: CanLink) -> None:
        v, w = self._setpoint
        link.send("MotionCommand", LinearVelocity=round(v), AngularVelocity=round(w, 3),
                  LateralVelocity=0, SteeringAngle=0)

    async def _command_loop(self, link: CanLink) -> None:
        """The heartbeat on ``link`` (this connection's; closed under it, a send fails and latches NotConnected):
        the motion command every period on an absolute schedule, and the feedback watchdog."""
        loop = asyncio.get_running_loop()
        period = self._can.command_period_s
        next_t = loop.time()
        while True:
            try:
                self._send_setpoint(link)
            except (can.CanError, CanFrameError) as e:
                self._latch(NotConnected(self.name, f"cannot send on CAN: {e}"))
            self.command_times.append(loop.time())
            silent_s = loop.time() - self._last_status_t
            if silent_s > self._can.feedback_timeout_s:
                self._latch(DeviceTimeout(self.name, f"no status frame for {silent_s:.3f} s (link lost)"))
            next_t += period
            now = loop.time()
            if next_t < now - period:  # fell far behind (stalled loop): restart the schedule
                next_t = now
            await asyncio.sleep(max(0.0, next_t - now))

    async def _receive(self, link: CanLink) -> None:
        while True:
            try:
                name, sig, _ = await link.recv()
            except CanFrameError as e:
                self._latch(DeviceFault(self.name, f"malformed CAN frame: {e}"))
                continue
            except can.CanError as e:
                self._latch(NotConnected(self.name, f"CAN receive failed: {e}"))
                return
            if name == "SystemStatus":
                self._on_system_status(sig)
            elif name == "MotionState":
                self._motion = sig
            elif name == "Odometry":
                self._on_odometry(int(sig["LeftWheelOdometry"]), int(sig["RightWheelOdometry"]))
                self._wake()
            elif name.startswith("MotorLowRate"):
                self._on_driver_state(name[-1], int(sig["DriverState"]))

    def _on_system_status(self, sig: dict[str, float]) -> None:
        self._system = sig
        self._last_status_t = asyncio.get_running_loop().time()
        state, code, mode = int(sig["VehicleState"]), int(sig["ErrorCode"]), int(sig["ControlMode"])
        self._heard = self._heard or not code & HOST_COMMUNICATION
        not_yet = 0 if self._heard else HOST_COMMUNICATION  # no command heard yet: no fault of the link
        errors = bit_names(code & ~not_yet, ERROR_BITS)
        rc_lost = bool(code & RC_LOST)
        if rc_lost and mode == MODE_RC:
            errors.append(RC_LOST_NAME)
        if state == 1:
            self._latch(SafetyStop(self.name, "chassis emergency stop"))
        elif errors or (state == 2 and not code & (not_yet | RC_LOST)):
            self._latch(DeviceFault(self.name, f"chassis error 0x{code:04X}: {', '.join(errors) or 'exception'}"))
        elif mode != MODE_CAN and self._commanding:
            self._latch(DeviceFault(self.name, f"chassis left CAN mode ({CONTROL_MODES.get(mode, mode)} has control)"))
        warnings = bit_names(code, WARNING_BITS) + ([RC_LOST_NAME] if rc_lost and mode != MODE_RC else [])
        self._warn("system", ", ".join(warnings))

    def _on_driver_state(self, motor: str, state: int) -> None:
        """A motor driver's state bits: a fault latches, a warning is kept and logged."""
        if state & DRIVER_FAULT_MASK:
            problems = ", ".join(bit_names(state, DRIVER_STATE_BITS))
            self._latch(DeviceFault(self.name, f"motor {motor} driver: {problems}"))
        warnings = bit_names(state, DRIVER_WARNING_BITS)
        self._warn(f"motor {motor}", f"motor {motor} driver: {', '.join(warnings)}" if warnings else "")

    def _warn(self, source: str, text: str) -> None:
        """Keep what ``source`` warns of now (empty: nothing) for ``status()``; log it when it changes."""
        if text == self._warnings.get(source, ""):
            return
        if text:
            self._warnings[source] = text
            log.warning("%s: %s", self.name, text)
        elif self._warnings.pop(source, None) is not None:
            log.info("%s: %s warning cleared", self.name, source)

    def _on_odometry(self, left: int, right: int) -> None:
        """Dead-reckon the wheel travel (raw counts; a counter that wrapped counts on) into the pose (midpoint rule;
        effective skid-steer track)."""
        if self._wheels is not None:
            scale = self._can.odometry_mm_per_count
            dl, dr = counter_delta(left, self._wheels[0]) * scale, counter_delta(right, self._wheels[1]) * scale
            ds, dth = (dl + dr) / 2, (dr - dl) / self._can.odometry_track_mm
            p = self._pose
            mid = p.heading_rad + dth / 2
            self._pose = ChassisPose(p.x_mm + ds * math.cos(mid), p.y_mm + ds * math.sin(mid),
                                     wrap_angle(p.heading_rad + dth))
        self._wheels = (left, right)
