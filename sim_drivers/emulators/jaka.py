"""JAKA controller emulator: the JSON command port and the status stream over real TCP sockets.

Motion runs in simulated time (``time_scale`` wall seconds per simulated second) through a swappable motion
model; poses come from :class:`tandemscan.pipeline.kinematics.ArmKinematics`. ``on_joints`` is called with
every new joint vector (rad), so the emulator can move the simulated world's arm. Faults are injected through
:class:`JakaFaults`, which may be changed while the emulator runs.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from tandemscan.config.models import ArmConfig
from tandemscan.drivers.json_stream import JsonFramingError, JsonObjectFramer, encode
from tandemscan.pipeline.frames import from_rpy, to_rpy
from tandemscan.pipeline.kinematics import ArmKinematics
from tandemscan.sim_drivers.emulators.tcp_server import TcpService

log = logging.getLogger(__name__)


@dataclass
class JakaFaults:
    """Fault injection; every flag can be flipped while a client is connected."""

    reply_delay_s: float = 0.0  # every reply waits this long (slow controller)
    silent: bool = False  # commands are read but never answered
    truncate_next_reply: bool = False  # half a reply, then the command connection closes
    disconnect_on_move: bool = False  # every connection drops as soon as a move starts
    estop: bool = False  # emergency stop pressed: motion halts, status reports it, moves are refused
    nan_in_status: bool = False  # status stream sends a NaN joint angle


class JointMotion:
    """Joint-space motion at constant joint speed in simulated seconds; replace for a richer profile."""

    def __init__(self, q_deg: np.ndarray):
        self._start = self._target = np.asarray(q_deg, float)
        self._t0 = 0.0
        self._duration = 0.0

    def command(self, target_deg: np.ndarray, speed_deg_s: float, now_s: float) -> None:
        self._start = self.position(now_s)
        self._target = np.asarray(target_deg, float)
        self._t0 = now_s
        self._duration = float(np.max(np.abs(self._target - self._start))) / max(speed_deg_s, 1e-9)

    def position(self, now_s: float) -> np.ndarray:
        if self._duration <= 0:
            return self._target.copy()
        f = min(max((now_s - self._t0) / self._duration, 0.0), 1.0)
        return self._start + f * (self._target - self._start)

    def in_position(self, now_s: float) -> bool:
        return now_s >= self._t0 + self._duration

    def halt(self, now_s: float) -> None:
        q = self.position(now_s)
        self._start = self._target = q
        self._duration = 0.0


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
        on_joints: Callable[[np.ndarray], None] | None = None,
        kinematics: ArmKinematics | None = None,
    ):
        self.config = config
        self.kinematics = kinematics or ArmKinematics(config)
        self.faults = JakaFaults()
        self.status_period_s = status_period_s
        self.time_scale = time_scale
        self.on_joints = on_joints
        q0 = np.zeros(6) if initial_joints_rad is None else np.asarray(initial_joints_rad, float)
        self.motion = JointMotion(np.degrees(q0))
        self.powered = False
        self.enabled = False
        self.commands: list[str] = []  # every command name received, in order
        self._commands = TcpService(self._serve_commands, host, command_port, exclusive=True)
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

    def sim_time(self) -> float:
        """Simulated seconds since start: wall time / ``time_scale``, integrated so the scale may change while
        running; a zero scale makes motion instant."""
        wall = asyncio.get_running_loop().time()
        self._sim_s += (wall - self._wall_s) / self.time_scale if self.time_scale > 0 else 0.0
        self._wall_s = wall
        return self._sim_s

    def joints_deg(self) -> np.ndarray:
        q = self.motion.position(self.sim_time())
        if self.on_joints is not None:
            self.on_joints(np.radians(q))
        return q

    def tcp_pose(self, q_deg: np.ndarray) -> list[float]:
        xyz, rpy = to_rpy(self.kinematics.forward(np.radians(q_deg)))
        return [*xyz.tolist(), *np.degrees(rpy).tolist()]

    def status_message(self) -> dict:
        if self.faults.estop:
            self.motion.halt(self.sim_time())
        q = self.joints_deg()
        joints: list[object] = q.tolist()
        if self.faults.nan_in_status:
            joints[0] = float("nan")
        return {
            "joint_actual_position": joints,
            "actual_position": self.tcp_pose(q),
            "enabled": self.enabled,
            "powered_on": int(self.powered),
            "inpos": self.motion.in_position(self.sim_time()),
            "emergency_stop": int(self.faults.estop),
            "protective_stop": 0,
            "on_soft_limit": 0,
            "errcode": "0x0",
            "errmsg": "",
            "task_state": 4 if self.enabled else 1,
            "paused": False,
        }

    # ------------------------------------------------------------------ status port

    async def _serve_status(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        while True:
            msg = self.status_message()
            writer.write(json.dumps(msg).encode() if self.faults.nan_in_status else encode(msg))
            await writer.drain()
            await asyncio.sleep(self.status_period_s)

    # ------------------------------------------------------------------ command port

    async def _serve_commands(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
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
                reply = {"cmdName": name, "errorCode": "0", "errorMsg": "", **await self._execute(name, req)}
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
                writer.write(raw)
                await writer.drain()
                if name in ("joint_move", "moveL", "end_move") and self.faults.disconnect_on_move:
                    await self._status.drop_clients()
                    return  # ends this handler, which closes the command connection

    async def _execute(self, name: str, req: dict) -> dict:
        """Apply one command; returns the reply's data, with ``errorCode``/``errorMsg`` on failure."""
        now = self.sim_time()
        if name == "power_on":
            self.powered = True
        elif name == "power_off":
            self.powered = self.enabled = False
        elif name == "enable_robot":
            if not self.powered:
                return _error("1", "robot is not powered on")
            self.enabled = True
        elif name == "disable_robot":
            self.enabled = False
        elif name == "get_robot_state":
            return {"power": "powered_on" if self.powered else "powered_off",
                    "enable": "robot_enabled" if self.enabled else "robot_disabled"}
        elif name == "get_joint_pos":
            return {"joint_pos": self.joints_deg().tolist()}
        elif name == "get_tcp_pos":
            return {"tcp_pos": self.tcp_pose(self.joints_deg())}
        elif name == "get_data":
            return self.status_message()
        elif name in ("stop_program", "clear_error", "quit"):
            self.motion.halt(now)
        elif name in ("joint_move", "moveL", "end_move"):
            return await self._move(name, req, now)
        else:
            return _error("1", f"unknown command {name!r}")
        return {}

    async def _move(self, name: str, req: dict, now: float) -> dict:
        if self.faults.estop:
            return _error("1", "emergency stop active")
        if not self.enabled:
            return _error("1", "robot is not enabled")
        current = self.motion.position(now)
        try:
            if name == "joint_move":
                target = np.asarray(req["jointPosition"], float) + (current if req.get("relFlag") else 0.0)
                speed = float(req.get("speed", self.config.joint_speed_deg_s))
            else:
                pose = np.asarray(req["cartPosition" if name == "moveL" else "endPosition"], float)
                if req.get("relFlag"):
                    pose = pose + np.asarray(self.tcp_pose(current))
                reach_mm = float(np.sum(np.abs(self.config.dh_a_mm)) + np.sum(np.abs(self.config.dh_d_mm)))
                if np.linalg.norm(pose[:3]) > reach_mm:
                    return _error("2", "target beyond the arm's reach")
                q = await asyncio.to_thread(
                    self.kinematics.inverse, from_rpy(pose[:3], np.radians(pose[3:])), np.radians(current)
                )
                if q is None:
                    return _error("2", "inverse kinematics failed")
                target = np.degrees(q)
                speed = self.config.joint_speed_deg_s
        except (KeyError, TypeError, ValueError) as e:
            return _error("1", f"bad parameters: {e}")
        if target.shape != (6,) or not np.all(np.isfinite(target)):
            return _error("1", "bad target")
        if not self.kinematics.within_limits(np.radians(target)):
            return _error("1", "joint target outside limits")
        self.motion.command(target, speed if self.time_scale > 0 else math.inf, now)
        return {}


def _error(code: str, message: str) -> dict:
    return {"errorCode": code, "errorMsg": message}
