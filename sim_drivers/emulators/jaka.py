"""JAKA controller emulator: the JSON command port and the status stream over real TCP sockets.

Motion runs in simulated time (``time_scale`` wall seconds per simulated second) through a swappable motion
model; poses come from :class:`tandemscan.pipeline.geometry.kinematics.ArmKinematics`. ``on_joints(q_rad, moving)``
is called with every joint vector the controller reports, so the emulator can move the simulated world's arm.
Faults are injected through :class:`JakaFaults`, which may be changed while the emulator runs.

Vendor behaviour it can be told to show (:class:`JakaBehaviour`, docs/drivers.md): ``power_on`` and
``enable_robot`` that complete seconds after their reply, replies and status objects cut into small TCP
segments (and status objects coalesced across segments), ``errorCode`` as a number, status objects padded to
the size of a real controller's (5-9 kB), moves answered only when they are done (as client code that treats
``joint_move`` as blocking sees it; other commands, ``stop_program`` too, are served meanwhile). Refused motion
commands answer ``errorCode`` 2 whatever the reason, as the controller's generic "call failed" code. A tool and a
user frame selected on the controller (:meth:`JakaEmulator.select_frames`) apply to every Cartesian pose, as
``current_tool_id`` / ``current_user_id`` in the status say.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from tandemscan.config.models import ArmConfig
from tandemscan.drivers.json_stream import JsonFramingError, JsonObjectFramer, encode
from tandemscan.drivers.tasks import cancel_and_wait
from tandemscan.pipeline.geometry.frames import from_rpy, to_rpy
from tandemscan.pipeline.geometry.kinematics import ArmKinematics
from tandemscan.sim_drivers.emulators.tcp_server import TcpService

log = logging.getLogger(__name__)


@dataclass
class JakaFaults:
    """Fault injection; every flag can be flipped while a client is connected."""

    reply_delay_s: float = 0.0  # every reply waits this long (slow controller)
    silent: bool = False  # commands are read and carried out but never answered
    ignore_commands: bool = False  # commands are read and dropped: neither carried out nor answered
    truncate_next_reply: bool = False  # half a reply, then the command connection closes
    disconnect_on_move: bool = False  # every connection drops as soon as a move starts
    estop: bool = False  # emergency stop pressed: motion halts, status reports it, moves are refused
    protective_stop: bool = False  # protective stop (collision): as estop, reported as protective_stop
    nan_in_status: bool = False  # status stream sends a NaN joint angle
    status_silent: bool = False  # the status stream stops pushing while its connection stays open
    controller_error: str = ""  # a controller error (e.g. "0x10030001"): motion halts, status reports it as
    #                             errcode / errmsg, moves are refused until clear_error


@dataclass(frozen=True)
class JakaBehaviour:
    """How closely the emulator follows a real controller; the defaults are the quick, forgiving peer."""

    power_on_delay_s: float = 0.0  # wall seconds from power_on to powered (real: about 2 s)
    enable_delay_s: float = 0.0  # wall seconds from enable_robot to enabled (real: about 0.5 s)
    segment_bytes: int = 0  # > 0: every write goes out in TCP segments of at most this many bytes
    numeric_error_codes: bool = False  # errorCode as a number (0, 2) instead of a string
    status_bytes: int = 0  # > 0: status objects padded with vendor keys (din, dout, ain, ...) to about this size
    move_start_delay_s: float = 0.0  # wall seconds from a move's reply until the arm starts it; meanwhile the
    # status still shows the last move's inpos (a real controller plans first and pushes every 8 ms)
    knows_kine_inverse: bool = True  # False: an older controller that answers kine_inverse as an unknown command
    reply_moves_when_done: bool = False  # True: a move's reply comes when the motion ends (or is stopped)
    status_leaves_out: tuple[str, ...] = ()  # status keys not pushed (the content is a setting of the controller)
    refuse_second_client: bool = False  # True: a new command connection is closed at once while one is served
    # (until the controller has let the last one go), instead of replacing it


class JointMotion:
    """Joint-space motion at constant joint speed in simulated seconds; replace for a richer profile."""

    def __init__(self, q_deg: np.ndarray):
        self._start = self._target = np.asarray(q_deg, float)
        self._t0 = 0.0
        self._duration = 0.0

    def command(self, target_deg: np.ndarray, speed_deg_s: float, now_s: float, start_delay_s: float = 0.0) -> None:
        """Move to ``target_deg`` at ``speed_deg_s``, starting ``start_delay_s`` after ``now_s`` (simulated s)."""
        self._start = self.position(now_s)
        self._target = np.asarray(target_deg, float)
        self._t0 = now_s + start_delay_s
        self._duration = float(np.max(np.abs(self._target - self._start))) / max(speed_deg_s, 1e-9)

    def position(self, now_s: float) -> np.ndarray:
        if self._duration <= 0:
            return self._target.copy()
        f = min(max((now_s - self._t0) / self._duration, 0.0), 1.0)
        return self._start + f * (self._target - self._start)

    def in_position(self, now_s: float) -> bool:
        """At the target, or not yet started (the previous move's flag, as a controller's status shows it)."""
        return self.done(now_s) or now_s < self._t0

    def done(self, now_s: float) -> bool:
        """The last move is over: at its target, or halted."""
        return now_s >= self._t0 + self._duration

    def halt(self, now_s: float) -> None:
        q = self.position(now_s)
        self._start = self._target = q
        self._t0, self._duration = now_s, 0.0


class JakaEmulator:
    """Serves the command port (one client; a new one replaces the old) and the status stream."""

    def __init__(
        self,
        config: ArmConfig,
        host: str = "127.0.0.1",
        command_port: int = 0,
        status_port: int = 0,
        status_period_s: float = 0.008,
        time_scale: float = 0.01,
        initial_joints_rad: np.ndarray | None = None,
        on_joints: Callable[[np.ndarray, bool], None] | None = None,
        kinematics: ArmKinematics | None = None,
        behaviour: JakaBehaviour | None = None,
    ):
        self.config = config
        self.kinematics = kinematics or ArmKinematics(config)
        self.faults = JakaFaults()
        self.behaviour = behaviour or JakaBehaviour()
        self.status_period_s = status_period_s
        self.time_scale = time_scale
        self.on_joints = on_joints
        q0 = np.zeros(6) if initial_joints_rad is None else np.asarray(initial_joints_rad, float)
        self.motion = JointMotion(np.degrees(q0))
        self._powered_at = math.inf  # loop time at which power_on / enable_robot take effect
        self._enabled_at = math.inf
        self.commands: list[str] = []  # every command name received, in order
        # the selected tool (id, T_E_tool) and user frame (id, T_B_U), mm: Cartesian poses are the tool's in it
        self.tool: tuple[int, np.ndarray] = (0, np.eye(4))
        self.user_frame: tuple[int, np.ndarray] = (0, np.eye(4))
        self._commands = TcpService(self._serve_commands, host, command_port, exclusive=True,
                                    refuse_second=lambda: self.behaviour.refuse_second_client)
        self._status = TcpService(self._serve_status, host, status_port)
        self._sim_s = 0.0
        self._wall_s = 0.0

    # ------------------------------------------------------------------ lifecycle

    async def start(self) -> tuple[int, int]:
        """Listen; returns ``(command_port, status_port)``."""
        self._wall_s = asyncio.get_running_loop().time()
        return await self._commands.start(), await self._status.start()

    async def stop(self) -> None:
        await self._commands.stop()
        await self._status.stop()

    async def drop_connections(self) -> None:
        """Close every client connection now (a link loss)."""
        await self._commands.drop_clients()
        await self._status.drop_clients()

    # ------------------------------------------------------------------ state

    @property
    def powered(self) -> bool:
        return asyncio.get_running_loop().time() >= self._powered_at

    @property
    def enabled(self) -> bool:
        return self.powered and asyncio.get_running_loop().time() >= self._enabled_at

    def set_power(self, powered: bool, enabled: bool) -> None:
        """Power and enable the arm at once (tests), or switch it off."""
        now = asyncio.get_running_loop().time()
        self._powered_at = now if powered else math.inf
        self._enabled_at = now if enabled else math.inf

    def sim_time(self) -> float:
        """Simulated seconds since start: wall time / ``time_scale``, integrated so the scale may change while
        running; a zero scale makes motion instant."""
        wall = asyncio.get_running_loop().time()
        self._sim_s += (wall - self._wall_s) / self.time_scale if self.time_scale > 0 else 0.0
        self._wall_s = wall
        return self._sim_s

    def joints_deg(self) -> np.ndarray:
        now = self.sim_time()
        q = self.motion.position(now)
        if self.on_joints is not None:
            self.on_joints(np.radians(q), not self.motion.in_position(now))
        return q

    def select_frames(self, tool: tuple[int, np.ndarray], user_frame: tuple[int, np.ndarray]) -> None:
        """Select a tool ``(id, T_E_tool)`` and a user frame ``(id, T_B_U)`` (mm), as on the pendant."""
        self.tool, self.user_frame = tool, user_frame

    def tcp_pose(self, q_deg: np.ndarray) -> list[float]:
        """The selected tool's pose in the selected user frame: ``[x, y, z mm, rx, ry, rz deg]``."""
        T_B_E = self.kinematics.forward(np.radians(q_deg))
        xyz, rpy = to_rpy(np.linalg.inv(self.user_frame[1]) @ T_B_E @ self.tool[1])
        return [*xyz.tolist(), *np.degrees(rpy).tolist()]

    def flange_target(self, pose: np.ndarray) -> np.ndarray:
        """``T_B_E`` (mm) that puts the selected tool at ``pose`` ``[x, y, z mm, rx, ry, rz deg]`` in the user
        frame."""
        return self.user_frame[1] @ from_rpy(pose[:3], np.radians(pose[3:])) @ np.linalg.inv(self.tool[1])

    def status_message(self) -> dict:
        if self.faults.estop or self.faults.protective_stop or self.faults.controller_error:
            self.motion.halt(self.sim_time())
        q = self.joints_deg()
        joints: list[object] = q.tolist()
        if self.faults.nan_in_status:
            joints[0] = float("nan")
        msg = {
            "joint_actual_position": joints,
            "actual_position": self.tcp_pose(q),
            "enabled": self.enabled,
            "powered_on": int(self.powered),
            "inpos": self.motion.in_position(self.sim_time()),
            "emergency_stop": int(self.faults.estop),
            "protective_stop": int(self.faults.protective_stop),
            "on_soft_limit": 0,
            "current_tool_id": self.tool[0],
            "current_user_id": self.user_frame[0],
            "errcode": self.faults.controller_error or "0x0",
            "errmsg": "servo error (emulated)" if self.faults.controller_error else "",
            "task_state": 4 if self.enabled else 1,
            "paused": False,
        }
        for key in self.behaviour.status_leaves_out:
            msg.pop(key, None)
        if self.behaviour.status_bytes > 0:
            msg.update(vendor_padding(self.behaviour.status_bytes - len(encode(msg))))
        return msg

    # ------------------------------------------------------------------ status port

    async def _serve_status(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        pending = b""  # with segments, a message's tail goes out together with the next message's head
        while True:
            if not self.faults.status_silent:
                msg = self.status_message()
                pending += json.dumps(msg).encode() if self.faults.nan_in_status else encode(msg)
                size = self.behaviour.segment_bytes
                cut = len(pending) if size <= 0 else len(pending) - len(pending) % size
                await self._send(writer, pending[:cut])
                pending = pending[cut:]
            await asyncio.sleep(self.status_period_s)

    async def _send(self, writer: asyncio.StreamWriter, data: bytes) -> None:
        """Write ``data`` in segments of ``behaviour.segment_bytes`` (each drained apart), or at once."""
        size = self.behaviour.segment_bytes if self.behaviour.segment_bytes > 0 else max(len(data), 1)
        for i in range(0, len(data), size):
            writer.write(data[i : i + size])
            await writer.drain()
            if size < len(data):
                await asyncio.sleep(0)

    # ------------------------------------------------------------------ command port

    async def _serve_commands(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        sending = asyncio.Lock()  # one reply at a time on the wire (a move's may be sent later, when it is done)
        deferred: set[asyncio.Task] = set()
        try:
            await self._serve_requests(reader, writer, sending, deferred)
        finally:
            for task in deferred:
                await cancel_and_wait(task)

    async def _serve_requests(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                              sending: asyncio.Lock, deferred: set[asyncio.Task]) -> None:
        framer = JsonObjectFramer()
        while True:
            data = await reader.read(65536)
            if not data:
                return
            try:
                requests = framer.feed(data)
            except JsonFramingError as e:
                log.warning("jaka emulator: bad request: %s", e)
                requests = [{"cmdName": "", "bad": str(e)}]
            for req in requests:
                name = str(req.get("cmdName", ""))
                self.commands.append(name)
                if self.faults.ignore_commands:
                    continue
                reply = {"cmdName": name, "errorCode": "0", "errorMsg": "", **await self._execute(name, req)}
                if self.behaviour.numeric_error_codes:
                    reply["errorCode"] = int(reply["errorCode"])
                if self.faults.silent:
                    continue
                if self.faults.reply_delay_s:
                    await asyncio.sleep(self.faults.reply_delay_s)
                raw = encode(reply)
                if self.faults.truncate_next_reply:
                    self.faults.truncate_next_reply = False
                    writer.write(raw[: len(raw) // 2])
                    await writer.drain()
                    return
                is_move = name in ("joint_move", "moveL", "end_move")
                if is_move and self.behaviour.reply_moves_when_done and str(reply["errorCode"]) == "0":
                    task = asyncio.create_task(self._reply_when_done(writer, raw, sending))
                    deferred.add(task)
                    task.add_done_callback(deferred.discard)
                else:
                    async with sending:
                        await self._send(writer, raw)
                if is_move and self.faults.disconnect_on_move:
                    await self._status.drop_clients()
                    return  # ends this handler, which closes the command connection

    async def _reply_when_done(self, writer: asyncio.StreamWriter, raw: bytes, sending: asyncio.Lock) -> None:
        """Send a move's reply once the motion is over (at its target, or stopped)."""
        while not self.motion.done(self.sim_time()):
            await asyncio.sleep(self.status_period_s)
        async with sending:
            with contextlib.suppress(ConnectionError, OSError):  # the client went away meanwhile
                await self._send(writer, raw)

    async def _execute(self, name: str, req: dict) -> dict:
        """Apply one command; returns the reply's data, with ``errorCode``/``errorMsg`` on failure."""
        now = self.sim_time()
        loop_now = asyncio.get_running_loop().time()
        if name == "power_on":
            if not self.powered:
                self._powered_at = min(self._powered_at, loop_now + self.behaviour.power_on_delay_s)
        elif name == "power_off":
            self.set_power(False, False)
        elif name == "enable_robot":
            if not self.powered:
                return _error("1", "robot is not powered on")
            if not self.enabled:
                self._enabled_at = min(self._enabled_at, loop_now + self.behaviour.enable_delay_s)
        elif name == "disable_robot":
            self._enabled_at = math.inf
        elif name == "get_robot_state":
            return {"power": "powered_on" if self.powered else "powered_off",
                    "enable": "robot_enabled" if self.enabled else "robot_disabled"}
        elif name == "get_joint_pos":
            return {"joint_pos": self.joints_deg().tolist()}
        elif name == "get_tcp_pos":
            return {"tcp_pos": self.tcp_pose(self.joints_deg())}
        elif name == "get_data":
            return self.status_message()
        elif name == "kine_inverse" and self.behaviour.knows_kine_inverse:
            return await self._kine_inverse(req)
        elif name in ("stop_program", "clear_error", "quit"):
            self.motion.halt(now)
            if name == "clear_error":
                self.faults.controller_error = ""
        elif name in ("joint_move", "moveL", "end_move"):
            return await self._move(name, req, now)
        else:
            return _error("1", f"unknown command {name!r}")
        return {}

    async def _kine_inverse(self, req: dict) -> dict:
        try:
            pose = np.asarray(req["cartPosition"], float)
            ref = np.radians(np.asarray(req["jointPosition"], float))
        except (KeyError, TypeError, ValueError) as e:
            return _error("1", f"bad parameters: {e}")
        q = await self._solve(pose, ref)
        if q is None or not self.kinematics.within_limits(q):
            return _error("2", "inverse kinematics failed")
        return {"jointPosition": np.degrees(q).tolist()}

    async def _solve(self, pose: np.ndarray, ref_rad: np.ndarray) -> np.ndarray | None:
        """Joints (rad) near ``ref_rad`` that put the selected tool at ``pose`` ``[x, y, z mm, rx, ry, rz deg]`` in
        the selected user frame; None if none."""
        reach_mm = float(np.sum(np.abs(self.config.dh_a_mm)) + np.sum(np.abs(self.config.dh_d_mm)))
        T_B_E = self.flange_target(pose)
        if np.linalg.norm(T_B_E[:3, 3]) > reach_mm:
            return None
        return await asyncio.to_thread(self.kinematics.inverse, T_B_E, ref_rad)

    def _joint_speed_for_path(self, path_mm: float, speed_mm_s: float, step_deg: np.ndarray) -> float:
        """The joint speed (deg/s) at which the joint interpolation by ``step_deg`` takes as long as the flange's
        straight ``path_mm`` at ``speed_mm_s`` (the emulator models a linear move's duration, not its path's
        shape), at most the arm's joint speed; ValueError for a speed not above zero."""
        if not speed_mm_s > 0:
            raise ValueError(f"linear speed {speed_mm_s} mm/s")
        largest_deg = float(np.max(np.abs(step_deg)))
        return min(self.config.joint_speed_deg_s, largest_deg * speed_mm_s / path_mm if path_mm > 0 else math.inf)

    async def _move(self, name: str, req: dict, now: float) -> dict:
        if self.faults.estop:
            return _error("2", "emergency stop active")
        if self.faults.protective_stop:
            return _error("2", "protective stop active")
        if self.faults.controller_error:
            return _error("2", f"controller error {self.faults.controller_error}")
        if not self.enabled:
            return _error("2", "robot is not enabled")
        current = self.motion.position(now)
        try:
            if name == "joint_move":
                target = np.asarray(req["jointPosition"], float) + (current if req.get("relFlag") else 0.0)
                speed = float(req.get("speed", self.config.joint_speed_deg_s))
            else:
                pose = np.asarray(req["cartPosition" if name == "moveL" else "endPosition"], float)
                start = np.asarray(self.tcp_pose(current))     # [x, y, z mm, rx, ry, rz deg]
                if req.get("relFlag"):
                    pose = pose + start
                q = await self._solve(pose, np.radians(current))
                if q is None:
                    return _error("2", "inverse kinematics failed")
                target = np.degrees(q)
                speed = self.config.joint_speed_deg_s
                if name == "moveL":   # the flange's straight path at the commanded speed (mm/s), joints permitting
                    speed = self._joint_speed_for_path(float(np.linalg.norm(pose[:3] - start[:3])),
                                                       float(req.get("speed", math.inf)), target - current)
        except (KeyError, TypeError, ValueError) as e:
            return _error("2", f"bad parameters: {e}")
        if target.shape != (6,) or not np.all(np.isfinite(target)):
            return _error("2", "bad target")
        if not self.kinematics.within_limits(np.radians(target)):
            return _error("2", "joint target outside limits")
        delay = self.behaviour.move_start_delay_s / self.time_scale if self.time_scale > 0 else 0.0
        self.motion.command(target, speed if self.time_scale > 0 else math.inf, now, delay)
        return {}


def _error(code: str, message: str) -> dict:
    return {"errorCode": code, "errorMsg": message}


def vendor_padding(n_bytes: int) -> dict:
    """Status keys a real controller also pushes (I/O images and diagnostics, zeros here), about ``n_bytes``
    of JSON in all; empty for ``n_bytes <= 0``."""
    pad: dict[str, object] = {}
    tiers = (("din", 144), ("dout", 144), ("ain", 66), ("aout", 66), ("tio_din", 8), ("tio_dout", 8))
    i = 0
    while n_bytes > 0:
        key, count = tiers[i % len(tiers)]
        name = key if i < len(tiers) else f"{key}_{i // len(tiers)}"
        values = [0.0 if key.startswith("a") else 0] * count
        pad[name] = values
        n_bytes -= len(encode({name: values}))
        i += 1
    return pad
