"""JAKA Zu arm over its TCP/IP protocol: JSON commands on one port, a pushed status stream on another.

Protocol facts (docs/drivers.md): requests ``{"cmdName": ..., ...}``; replies carry ``errorCode`` (``"0"``
success; a string, some firmware sends a number) and ``errorMsg``; a reply only means "received", so
``power_on``/``enable_robot`` are polled with ``get_robot_state`` until done and a move is complete when the
status stream shows ``inpos`` at the target. An error code is no reason: a refused Cartesian target is out of
reach only when ``kine_inverse`` answers that it has no solution; any other refusal is a fault with the
controller's text and the robot's state. The status stream is the link watchdog: a gap of
``status_gap_timeout_s`` while waiting on it is a lost link. Degrees and JAKA's fixed x-y-z Euler angles
exist only inside this module; the interface speaks radians, millimetres and 4x4 ``T_B_E``. The tool offset
on the controller must be zero, so that its TCP pose is the flange pose ``T_B_E``.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import math
from collections.abc import Callable

import numpy as np
from tandemscan.config.models import ArmConfig
from tandemscan.drivers.errors import (
    DeviceError,
    DeviceFault,
    DeviceTimeout,
    NotConnected,
    OutOfReach,
    SafetyStop,
)
from tandemscan.drivers.interfaces import DeviceState, DeviceStatus
from tandemscan.drivers.json_stream import JsonFramingError, JsonObjectFramer, encode
from tandemscan.drivers.tasks import cancel_and_wait
from tandemscan.pipeline.geometry.frames import from_rpy, pose_error, to_rpy

log = logging.getLogger(__name__)

_READ_CHUNK = 65536
_POWERED = ("powered_on", 1, True)
_ENABLED = ("robot_enabled", 1, True)
# A status stream silent for this many of its push periods is a lost link (where longer than status_gap_timeout_s)
STATUS_GAP_PERIODS = 4
# The push period is timed at connect as the median interval between this many first status messages
STATUS_PERIOD_SAMPLES = 4
# Moves: their reply means "received" on most firmware, "done" where the controller answers a move at its end
MOVE_COMMANDS = ("joint_move", "moveL", "end_move")
# The controller's tool and user frame the driver needs: 0 and 0, the flange in the base frame (status keys
# current_tool_id / current_user_id); poses and Cartesian targets are then the flange's T_B_E
FLANGE_TOOL_ID, BASE_USER_FRAME_ID = 0, 0
# A stop's new command connection closed at once by the controller is opened again after this long (s)
REOPEN_PERIOD_S = 0.05


def succeeded(reply: dict) -> bool:
    """True when ``errorCode`` means success: ``"0"`` or ``0`` (string or number, as firmware differs)."""
    return str(reply.get("errorCode")).strip() == "0"


def in_position(status: dict) -> bool:
    """The status's ``inpos``; true where the controller does not push it (the status content is a setting of the
    controller): completion then rests on the actual position at the target alone."""
    return bool(status.get("inpos", True))


def six_finite(value: object, what: str, device: str) -> np.ndarray:
    """``value`` as a float array of 6 finite numbers, else :class:`DeviceFault`."""
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as e:
        raise DeviceFault(device, f"{what} is not numeric: {value!r}") from e
    if arr.shape != (6,) or not np.all(np.isfinite(arr)):
        raise DeviceFault(device, f"{what} must be 6 finite numbers, got {value!r}")
    return arr


class JakaTcpArm:
    """The :class:`~tandemscan.drivers.interfaces.Arm` on a JAKA controller (settings in ``ArmConfig.jaka``)."""

    def __init__(self, config: ArmConfig, name: str = "arm"):
        self.name = name
        self._cfg = config
        self._net = config.jaka
        self._q_min = np.radians(config.joint_min_deg)
        self._q_max = np.radians(config.joint_max_deg)
        self._lock = asyncio.Lock()  # one command and its reply at a time on the command link
        # opening and closing the links: a connect, a close and a stop's reopening of the command link one at a
        # time (the controller serves one command client, a new one replaces the old); taken before ``_lock``
        self._link_lock = asyncio.Lock()
        self._cmd: tuple[asyncio.StreamReader, asyncio.StreamWriter] | None = None
        self._cmd_framer = JsonObjectFramer()
        self._cmd_backlog: list[dict] = []
        # replies still owed on this command link, by command: a move whose reply did not come within
        # reply_timeout_s (a controller that answers a move when it is done); read and checked when they come
        self._owed: collections.Counter[str] = collections.Counter()
        self._status_writer: asyncio.StreamWriter | None = None
        self._status_task: asyncio.Task | None = None
        self._status: dict | None = None
        self._status_event = asyncio.Event()
        self._status_error: DeviceError | None = None
        self._status_count = 0  # status messages received on this connection
        self._status_gap_s = config.jaka.status_gap_timeout_s  # the watchdog's gap, measured at connect
        self._status_arrivals: list[float] = []  # loop times (s) of this connection's first status messages

    # ------------------------------------------------------------------ lifecycle

    async def connect(self) -> None:
        """Open the command and status connections and wait for the first status message."""
        async with self._link_lock:
            await self._close_links()
            await self._open_links()

    async def _open_links(self) -> None:
        host, timeout = self._net.host, self._net.reply_timeout_s
        self._cmd = await self._open(host, self._net.command_port, timeout)
        status_reader, self._status_writer = await self._open(host, self._net.status_port, timeout)
        self._status_error, self._status_count, self._status_arrivals = None, 0, []
        self._status_task = asyncio.create_task(self._read_status(status_reader), name=f"{self.name}-status")
        self._status_gap_s = await self._measure_status_gap(timeout)
        log.info("%s: connected to %s:%d/%d (status watchdog gap %.3f s)", self.name, host, self._net.command_port,
                 self._net.status_port, self._status_gap_s)

    async def _measure_status_gap(self, timeout_s: float) -> float:
        """The status watchdog's gap (s): ``status_gap_timeout_s``, or :data:`STATUS_GAP_PERIODS` push periods
        where the controller pushes slower (its send period is a setting of the controller). The period is the
        median of the intervals between the arrivals of this connection's first :data:`STATUS_PERIOD_SAMPLES`
        status messages (a stall of the event loop stretches one and squeezes the next). The first message is
        awaited for up to ``timeout_s``, the others for up to ``3 timeout_s``; the supervisor's
        ``device_timeout_s`` bounds the whole connect."""
        await self._wait_status(lambda st: True, timeout_s, "the first status message", check_safety=False,
                                watchdog=False)
        await self._wait_status(lambda st: len(self._status_arrivals) >= STATUS_PERIOD_SAMPLES, 3 * timeout_s,
                                f"{STATUS_PERIOD_SAMPLES} status messages",
                                check_safety=False, watchdog=False)
        period_s = float(np.median(np.diff(self._status_arrivals)))
        return max(self._net.status_gap_timeout_s, STATUS_GAP_PERIODS * period_s)

    async def close(self) -> None:
        """Drop both connections; safe to call twice or after the peer vanished."""
        async with self._link_lock:
            await self._close_links()

    async def _close_links(self) -> None:
        task, self._status_task = self._status_task, None
        await cancel_and_wait(task)
        writers = [w for w in (self._cmd[1] if self._cmd else None, self._status_writer) if w is not None]
        self._cmd, self._status_writer, self._status = None, None, None
        self._cmd_framer, self._cmd_backlog, self._owed = JsonObjectFramer(), [], collections.Counter()
        for w in writers:
            w.close()
            with contextlib.suppress(OSError, TimeoutError):
                await asyncio.wait_for(w.wait_closed(), 1.0)

    async def status(self) -> DeviceStatus:
        st = self._status
        if self._cmd is None or st is None:
            return DeviceStatus(self.name, False, DeviceState.DISCONNECTED)
        if self._status_error is not None:
            return DeviceStatus(self.name, True, DeviceState.FAULT, {"error": str(self._status_error)})
        if st.get("emergency_stop") or st.get("protective_stop"):
            state = DeviceState.STOPPED
        elif str(st.get("errcode", "0x0")) not in ("0", "0x0"):
            state = DeviceState.FAULT
        else:
            state = DeviceState.IDLE if in_position(st) else DeviceState.MOVING
        detail = {k: st.get(k) for k in ("joint_actual_position", "enabled", "powered_on", "inpos", "errcode",
                                         "current_tool_id", "current_user_id")}
        return DeviceStatus(self.name, True, state, detail)

    # ------------------------------------------------------------------ verbs

    async def enable(self) -> None:
        """Power on, wait until powered, enable, wait until enabled (both polled with ``get_robot_state``)."""
        net = self._net
        if (await self._call("get_robot_state")).get("power") not in _POWERED:
            await self._call("power_on")
            await self._poll_robot_state("power", _POWERED, net.power_on_timeout_s)
        if (await self._call("get_robot_state")).get("enable") not in _ENABLED:
            await self._call("enable_robot")
            await self._poll_robot_state("enable", _ENABLED, net.enable_timeout_s)

    async def _poll_robot_state(self, key: str, done: tuple[object, ...], timeout_s: float) -> None:
        """Poll ``get_robot_state`` until ``key`` shows one of ``done``; :class:`DeviceTimeout` after ``timeout_s``."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        while True:
            value = (await self._call("get_robot_state")).get(key)
            if value in done:
                return
            if loop.time() > deadline:
                raise DeviceTimeout(self.name, f"robot state {key!r} still {value!r} after {timeout_s} s")
            await asyncio.sleep(self._net.state_poll_period_s)

    async def disable(self) -> None:
        """Disable the servos and power off."""
        await self._call("disable_robot")
        await self._call("power_off")

    async def move_joints(self, joints_rad: np.ndarray, timeout_s: float | None = None) -> None:
        """Joint move at ``ArmConfig.joint_speed_deg_s``; returns when the status stream shows it in position."""
        q = np.asarray(joints_rad, dtype=float)
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            raise ValueError(f"joints_rad must be 6 finite angles (rad), got {joints_rad!r}")
        if np.any(q < self._q_min - 1e-9) or np.any(q > self._q_max + 1e-9):
            raise OutOfReach(self.name, f"joint target {np.round(np.degrees(q), 3).tolist()} deg outside limits")
        target_deg = np.degrees(q)
        tol = self._net.inpos_tolerance_deg

        def arrived(st: dict) -> bool:
            actual = six_finite(st.get("joint_actual_position"), "joint_actual_position", self.name)
            return in_position(st) and float(np.max(np.abs(actual - target_deg))) <= tol

        await self._start_move(
            "joint_move", arrived, jointPosition=target_deg.tolist(), speed=self._cfg.joint_speed_deg_s,
            accel=self._net.joint_accel_deg_s2, relFlag=0,
        )
        await self._await_motion(arrived, timeout_s, "joint move")

    async def move_linear(self, T_B_E: np.ndarray, timeout_s: float | None = None) -> None:
        """Straight-line flange move to ``T_B_E`` (mm) at ``jaka.linear_speed_mm_s``; OutOfReach if IK fails."""
        T = np.asarray(T_B_E, dtype=float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError("T_B_E must be a finite 4x4 matrix")
        self._check_flange_frames("moveL")
        xyz, rpy = to_rpy(T)
        cart = [*xyz.tolist(), *np.degrees(rpy).tolist()]
        tol_mm, tol_rad = self._net.inpos_tolerance_mm, math.radians(self._net.inpos_tolerance_deg)

        def arrived(st: dict) -> bool:  # inpos alone may still be the last move's: the pose must be the target's
            actual = six_finite(st.get("actual_position"), "actual_position", self.name)
            dt_mm, dr_rad = pose_error(from_rpy(actual[:3], np.radians(actual[3:])), T)
            return in_position(st) and dt_mm <= tol_mm and dr_rad <= tol_rad

        await self._start_move(
            "moveL", arrived, cart, cartPosition=cart, speed=self._net.linear_speed_mm_s,
            accel=self._net.linear_accel_mm_s2, relFlag=0, tol=0,
        )
        await self._await_motion(arrived, timeout_s, "linear move")

    async def joints(self) -> np.ndarray:
        """Joint angles (rad) as the controller reports them."""
        reply = await self._call("get_joint_pos")
        return np.radians(six_finite(reply.get("joint_pos"), "joint_pos", self.name))

    async def flange_pose(self) -> np.ndarray:
        """``T_B_E`` (mm) from ``get_tcp_pos`` (x, y, z mm; rx, ry, rz deg, fixed x-y-z)."""
        self._check_flange_frames("get_tcp_pos")
        pose = six_finite((await self._call("get_tcp_pos")).get("tcp_pos"), "tcp_pos", self.name)
        return from_rpy(pose[:3], np.radians(pose[3:]))

    async def stop(self) -> None:
        """Stop the running motion (``stop_program``). Where the command link was dropped while the status stream
        still runs (a move whose reply never came may be running: the controller acts on a command before it
        replies), the stop goes out on a new command connection. A connect or close under way finishes first
        (their links are the stop's; the controller serves one command client)."""
        async with self._link_lock:
            if self._cmd is None and self._status_writer is not None:
                await self._stop_on_a_new_command_link()
            else:
                await self._call("stop_program")

    async def _stop_on_a_new_command_link(self) -> None:
        """Open a command connection and send ``stop_program`` on it. A controller that serves one command client
        may close a new connection at once while it has not yet let the dropped one go: tried again every
        :data:`REOPEN_PERIOD_S` until ``reply_timeout_s`` has passed."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self._net.reply_timeout_s
        while True:
            async with self._lock:
                self._cmd = await self._open(self._net.host, self._net.command_port, self._net.reply_timeout_s)
                self._cmd_framer, self._cmd_backlog, self._owed = JsonObjectFramer(), [], collections.Counter()
            log.warning("%s: command link reopened to stop the arm", self.name)
            try:
                await self._call("stop_program")
                return
            except NotConnected:
                if loop.time() > deadline:
                    raise
                log.info("%s: the controller closed the new command link (still serving the dropped one?); again",
                         self.name)
                await asyncio.sleep(REOPEN_PERIOD_S)

    async def clear_error(self) -> None:
        await self._call("clear_error")

    # ------------------------------------------------------------------ command port

    async def _open(self, host: str, port: int, timeout: float) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        try:
            async with asyncio.timeout(timeout):
                return await asyncio.open_connection(host, port)
        except TimeoutError as e:
            await self._close_links()
            raise DeviceTimeout(self.name, f"no connection to {host}:{port} within {timeout} s") from e
        except OSError as e:
            await self._close_links()
            raise NotConnected(self.name, f"cannot connect to {host}:{port}: {e}") from e

    async def _call(self, cmd: str, **params: object) -> dict:
        """Send one command, return its reply; a reply with a non-zero ``errorCode`` is a :class:`DeviceFault`."""
        reply = await self._request(cmd, self._net.reply_timeout_s, **params)
        assert reply is not None, f"{cmd} is a move: sent by _start_move"
        if not succeeded(reply):
            raise DeviceFault(self.name, _error_text(cmd, reply))
        return reply

    async def _request(self, cmd: str, timeout_s: float, **params: object) -> dict | None:
        """Send one command and return its reply as it is (``errorCode`` unchecked); link errors raise. A move
        (:data:`MOVE_COMMANDS`) whose reply does not come within ``timeout_s`` returns None: the controller may
        answer a move only when it is done (docs/drivers.md); the reply is owed and read when it comes."""
        async with self._lock:
            if self._cmd is None:
                raise NotConnected(self.name, f"{cmd}: not connected")
            reader, writer = self._cmd
            try:
                writer.write(encode({"cmdName": cmd, **params}))
                async with asyncio.timeout(timeout_s):
                    await writer.drain()
                    reply = await self._read_reply(reader, cmd)
            except TimeoutError as e:
                if cmd in MOVE_COMMANDS and not self._cmd_framer.pending:
                    self._owed[cmd] += 1
                    return None
                await self._drop_command_link()  # a late reply would be taken for the next command's
                raise DeviceTimeout(self.name, f"{cmd}: no reply within {timeout_s} s") from e
            except JsonFramingError as e:
                await self._drop_command_link()
                raise DeviceFault(self.name, f"{cmd}: malformed reply: {e}") from e
            except (ConnectionError, OSError) as e:
                await self._drop_command_link()
                raise NotConnected(self.name, f"{cmd}: connection lost: {e}") from e
            except DeviceError:
                await self._drop_command_link()
                raise
        if "errorCode" not in reply:
            raise DeviceFault(self.name, f"{cmd}: reply without errorCode: {reply!r}")
        return reply

    async def _read_reply(self, reader: asyncio.StreamReader, cmd: str) -> dict:
        """The reply to ``cmd``; replies owed to earlier moves (:meth:`_request`) are taken first, in order."""
        while True:
            while self._cmd_backlog:
                obj = self._cmd_backlog.pop(0)
                name = obj.get("cmdName")
                if self._owed[name] > 0:
                    self._owed[name] -= 1
                    if not succeeded(obj):
                        log.warning("%s: late reply: %s", self.name, _error_text(str(name), obj))
                    continue
                if name == cmd:
                    return obj
                log.warning("%s: ignoring reply to %r while waiting for %r", self.name, name, cmd)
            data = await reader.read(_READ_CHUNK)
            if not data:
                if self._cmd_framer.pending:
                    raise DeviceFault(self.name, f"{cmd}: connection closed inside a reply (truncated JSON)")
                raise NotConnected(self.name, f"{cmd}: controller closed the command connection")
            self._cmd_backlog.extend(self._cmd_framer.feed(data))

    async def _drop_command_link(self) -> None:
        if self._cmd is not None:
            writer = self._cmd[1]
            self._cmd = None
            writer.close()
            with contextlib.suppress(OSError, TimeoutError):
                await asyncio.wait_for(writer.wait_closed(), 1.0)

    # ------------------------------------------------------------------ status stream

    async def _read_status(self, reader: asyncio.StreamReader) -> None:
        framer = JsonObjectFramer()
        try:
            while True:
                data = await reader.read(_READ_CHUNK)
                if not data:
                    raise NotConnected(self.name, "status stream closed by the controller")
                arrived = asyncio.get_running_loop().time()
                for obj in framer.feed(data):
                    self._status = obj
                    self._status_count += 1
                    if len(self._status_arrivals) < STATUS_PERIOD_SAMPLES:
                        self._status_arrivals.append(arrived)
                    self._wake_status_waiters()
        except JsonFramingError as e:
            self._status_error = DeviceFault(self.name, f"malformed status message: {e}")
        except DeviceError as e:
            self._status_error = e
        except (ConnectionError, OSError) as e:
            self._status_error = NotConnected(self.name, f"status stream lost: {e}")
        self._wake_status_waiters()

    def _wake_status_waiters(self) -> None:
        """Wake everyone waiting for a status message; later waiters wait for the next one."""
        self._status_event.set()
        self._status_event = asyncio.Event()

    def _check_safety(self, st: dict) -> None:
        if st.get("emergency_stop"):
            raise SafetyStop(self.name, "emergency stop")
        if st.get("protective_stop"):
            raise SafetyStop(self.name, "protective stop")
        if str(st.get("errcode", "0x0")) not in ("0", "0x0"):
            raise DeviceFault(self.name, f"controller error {st.get('errcode')}: {st.get('errmsg', '')}")

    async def _wait_status(
        self, done: Callable[[dict], bool], timeout_s: float, what: str, check_safety: bool = True,
        watchdog: bool = True,
    ) -> dict:
        """The first status message for which ``done`` holds. With ``watchdog``, a gap of
        ``status_gap_timeout_s`` without any status message is a lost link (:class:`NotConnected`)."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        gap = self._status_gap_s if watchdog else math.inf
        while True:
            if self._status_error is not None:
                raise self._status_error
            event, st, count = self._status_event, self._status, self._status_count
            if st is not None:
                if check_safety:
                    self._check_safety(st)
                if done(st):
                    return st
            remaining = deadline - loop.time()
            try:
                if remaining <= 0:
                    raise TimeoutError
                async with asyncio.timeout(min(remaining, gap)):
                    await event.wait()
            except TimeoutError as e:
                if loop.time() >= deadline:
                    raise DeviceTimeout(self.name, f"{what} not seen within {timeout_s} s") from e
                await self._check_status_gap(count, gap)

    async def _check_status_gap(self, count: int, gap_s: float) -> None:
        """After a wait of ``gap_s`` without a message: unless one arrived meanwhile (the event loop may have
        been late to run the reader), the status link is lost, which later calls see too."""
        for _ in range(3):  # let a reader that was woken in the same loop turn deliver its message
            await asyncio.sleep(0)
        if self._status_count == count and self._status_error is None:
            self._status_error = NotConnected(self.name, f"no status message for {gap_s} s: controller silent "
                                                         f"or link lost")
            log.error("%s", self._status_error)

    async def _start_move(self, cmd: str, arrived: Callable[[dict], bool], cart: list[float] | None = None,
                          **params: object) -> None:
        """Refuse a move while the last status shows a stop or fault; else send it. A refused move is classified by
        what the controller says: :class:`OutOfReach` only when ``kine_inverse`` answers that it has no solution
        for the target ``cart`` (errorCode 2, docs/drivers.md); otherwise a :class:`DeviceFault` with the
        controller's text, the robot's power and enable state, and why reachability is not known. A move not
        answered within ``reply_timeout_s`` is taken as under way once the status shows the arm moving or
        ``arrived`` (a controller that answers a move when it is done); one that shows neither within as long
        again was not taken: :class:`DeviceTimeout`, the command link dropped."""
        if self._status is not None:
            self._check_safety(self._status)
        timeout_s = self._net.reply_timeout_s
        reply = await self._request(cmd, timeout_s, **params)
        if reply is None:
            try:
                await self._wait_status(lambda st: not in_position(st) or arrived(st), timeout_s, f"{cmd} under way")
            except DeviceTimeout as e:
                async with self._lock:
                    await self._drop_command_link()
                raise DeviceTimeout(self.name, f"{cmd}: no reply within {timeout_s} s and the arm did not start") from e
            log.info("%s: %s not answered within %s s but under way: a controller that answers a move when it is "
                     "done", self.name, cmd, timeout_s)
            return
        if succeeded(reply):
            return
        message = _error_text(cmd, reply)
        if cart is not None:
            ik = await self._request("kine_inverse", self._net.reply_timeout_s, cartPosition=cart,
                                     jointPosition=self._reference_joints_deg())
            assert ik is not None
            if _no_ik_solution(ik):
                raise OutOfReach(self.name, f"{message}; {_error_text('kine_inverse', ik)}")
            if not succeeded(ik):
                message += f"; reachability unknown: {_error_text('kine_inverse', ik)}"
        raise DeviceFault(self.name, message + self._not_ready_text())

    def _check_flange_frames(self, cmd: str) -> None:
        """Cartesian poses are the flange's in the base frame (``T_B_E``) only while the controller has tool
        :data:`FLANGE_TOOL_ID` and user frame :data:`BASE_USER_FRAME_ID` selected (status ``current_tool_id``,
        ``current_user_id``; a controller that does not push them is taken as set so): else a
        :class:`DeviceFault` before ``cmd`` is sent, naming what is selected."""
        st = self._status or {}
        wrong = [f"{what} {st[key]!r} (needs {want})" for key, want, what in (
            ("current_tool_id", FLANGE_TOOL_ID, "tool"), ("current_user_id", BASE_USER_FRAME_ID, "user frame"))
            if key in st and str(st[key]).strip() != str(want)]
        if wrong:
            raise DeviceFault(self.name, f"{cmd}: the controller has {' and '.join(wrong)} selected: Cartesian "
                                         "poses would not be the flange's in the base frame; select tool 0 and "
                                         "user frame 0 on the controller")

    def _not_ready_text(self) -> str:
        """What the last status says keeps the robot from moving (not powered, not enabled), or ''."""
        st = self._status or {}
        missing = [what for key, what in (("powered_on", "not powered"), ("enabled", "not enabled"))
                   if key in st and not st[key]]
        return f" (status: robot {', '.join(missing)})" if missing else ""

    def _reference_joints_deg(self) -> list[float]:
        """The joints of the last status message (deg): the reference solution for ``kine_inverse``."""
        st = self._status or {}
        return six_finite(st.get("joint_actual_position"), "joint_actual_position", self.name).tolist()

    async def _await_motion(self, arrived: Callable[[dict], bool], timeout_s: float | None, what: str) -> None:
        """Wait for ``arrived`` on the status stream; on any failure try to stop the arm, then re-raise."""
        timeout = self._cfg.timeout_s if timeout_s is None else timeout_s
        try:
            await self._wait_status(arrived, timeout, f"{what} completion")
        except BaseException as e:
            if self._cmd is not None:
                # a silent link would not answer either: then the attempt is bounded by the watchdog gap
                bound = self._status_gap_s if isinstance(e, NotConnected) else self._net.reply_timeout_s
                with contextlib.suppress(DeviceError):
                    await self._request("stop_program", bound)
            raise


def _no_ik_solution(reply: dict) -> bool:
    """Whether a ``kine_inverse`` reply says the target has no solution: errorCode 2, the controller's code for an
    inverse-kinematics failure; any other failure (an unknown command, bad parameters) says nothing of reach."""
    return str(reply.get("errorCode")).strip() == "2" and "unknown command" not in str(reply.get("errorMsg", ""))


def _error_text(cmd: str, reply: dict) -> str:
    return f"{cmd}: error {reply.get('errorCode')}: {reply.get('errorMsg', '')}"

