"""E-stop latency in the command-line path: ``tandemscan measure`` and ``tandemscan calibrate`` on the
hardware-in-the-loop cell (config/hil-cell.toml, every real driver against its emulator, ports made free).

For each command and each robot, the e-stop is raised (the world's safety input, which the hil glue mirrors
onto the Modbus emulator) as that robot's first motion after the second capture starts. Measured on the
emulators' side, from the Modbus discrete input's change: ``last_motion_command_ms``, the last motion command
a moving device received (a chassis: a non-zero velocity CAN frame; the arm: ``joint_move``/``moveL``; negative
= before the input changed) and ``stop_command_ms``, the first stop it received after (a zero-velocity frame,
``stop_program``). The requirement is motion stopped within one control period (20 ms at 50 Hz).

Usage: python benchmarks/estop_cli.py [--runs N]. The last line of output is one JSON object: per case
(``measure.arm``, ``measure.tracking_chassis``, ``calibrate.arm``, ``calibrate.tracking_chassis``) the exit
status, the latched reason and the two figures (median and max over the runs, ms).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from clean_exit import clean_exit_on_sigterm
from results import publish
from tandemscan.daemon import cli
from tandemscan.daemon.cli import cell_cmd
from tandemscan.daemon.plans import default_plan_path
from tandemscan.sim_drivers.hil_box import BOX_PLAN, write_hil_box_cell
from tandemscan.sim_drivers.world import SimWorld

CASES = (("measure", "arm"), ("measure", "tracking_chassis"), ("calibrate", "arm"), ("calibrate", "tracking_chassis"))


def hil_config_file(folder: Path) -> Path:
    """The box cell of ``sim_drivers.hil_box`` with the arm at 1/20 of real time (the shipped 1/500 ends most arm
    moves within a few ms, before an e-stop could land while the arm moves)."""
    return write_hil_box_cell(folder, default_plan_path(), "bench", arm_time_scale=0.05)


class EstopProbe:
    """Raises the e-stop on ``device``'s first motion after the second capture and timestamps, on the emulators,
    the input change and every motion and stop command (monotonic s)."""

    def __init__(self, device: str):
        self.device = device
        self.input_changed_s: float | None = None
        self.motion_s: list[float] = []
        self.stop_s: list[float] = []
        self.latched: str | None = None

    def attach(self, session) -> None:
        world = session.cell.simulation.world
        emulators = session.cell.simulation.emulators
        start = world.motion.start
        self._instrumented = False

        def started(robot: str) -> None:
            start(robot)
            if not self._instrumented:
                self._instrument(emulators.running)
            if world.captures >= 2 and not world.safety.estop and self._moving(robot, emulators.running):
                world.safety.estop = True

        world.motion.start = started
        self.session = session

    def _moving(self, robot: str, running: dict) -> bool:
        if self.device == "tracking_chassis":
            return robot == SimWorld.TRACKING_ROBOT
        return robot == SimWorld.MEASURE_ROBOT and running["measure_chassis"].velocity == (0.0, 0.0)

    def _instrument(self, running: dict) -> None:
        self._instrumented = True
        safety = running["safety"]
        press = safety.press_estop

        async def press_estop(pressed: bool = True) -> None:
            await press(pressed)
            if pressed and self.input_changed_s is None:
                self.input_changed_s = time.monotonic()

        safety.press_estop = press_estop
        emulator = running[self.device]
        if self.device == "arm":
            execute = emulator._execute

            async def traced(name: str, req: dict) -> dict:
                (self.motion_s if name in ("joint_move", "moveL") else self.stop_s if name == "stop_program"
                 else []).append(time.monotonic())
                return await execute(name, req)

            emulator._execute = traced
            return
        link = emulator._link
        recv = link.recv

        async def received():
            name, signals, message = await recv()
            if name == "MotionCommand":
                moving = signals["LinearVelocity"] != 0 or signals["AngularVelocity"] != 0
                (self.motion_s if moving else self.stop_s).append(time.monotonic())
            return name, signals, message

        link.recv = received

    def figures(self) -> dict:
        t0 = self.input_changed_s
        if t0 is None:
            return {"input_changed": False}
        stops = [t for t in self.stop_s if t >= t0]
        return {"last_motion_command_ms": round(1000 * (max(self.motion_s) - t0), 2) if self.motion_s else None,
                "stop_command_ms": round(1000 * (min(stops) - t0), 2) if stops else None}


def run_case(config_file: Path, command: str, device: str, out: Path) -> dict:
    probe = EstopProbe(device)
    build = cell_cmd._session

    def spied(config):
        session = build(config)
        probe.attach(session)
        return session

    cell_cmd._session = spied
    try:
        target = (["--out", str(out / "calibration.json")] if command == "calibrate"
                  else ["--plan", str(config_file.parent / BOX_PLAN), "--out", str(out)])
        status = cli.main([command, "--config", str(config_file), *target])
    finally:
        cell_cmd._session = build
    return {"exit_status": status, "latched": probe.session.supervisor.latched_reason, **probe.figures()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args()
    result = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for command, device in CASES:
            runs = [run_case(hil_config_file(folder), command, device, folder / f"{command}-{device}-{i}")
                    for i in range(args.runs)]
            case = {"exit_status": sorted({r["exit_status"] for r in runs}),
                    "latched": sorted({str(r["latched"]) for r in runs})}
            for key in ("last_motion_command_ms", "stop_command_ms"):
                values = [r[key] for r in runs if r.get(key) is not None]
                if values:
                    case[key] = {"median": float(np.median(values)), "max": float(np.max(values))}
            result[f"{command}.{device}"] = case
    publish("estop_cli", result)


if __name__ == "__main__":
    clean_exit_on_sigterm()
    main()
