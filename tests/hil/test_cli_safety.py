"""The supervisor's safety in the command-line path: ``tandemscan measure`` and ``tandemscan calibrate`` on the
hardware-in-the-loop cell (config/hil-cell.toml: every real driver against its emulator) stop every motion on an
e-stop raised on the Modbus emulator, end with one line and a non-zero status and keep what was measured; the
session's gate refuses motion while the session is closed and one robot while the other moves.

The e-stop is raised where the world's safety inputs are mirrored onto the Modbus emulator's discrete inputs
(``sim_drivers.hil``): at the first motion that starts after the job's second capture. The latency from the
input change to the last motion command is a figure, measured by ``benchmarks/estop_cli.py``."""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
import pytest
from tandemscan.daemon import cli
from tandemscan.daemon.cell.motion import Robot
from tandemscan.daemon.cell.session import CellSession
from tandemscan.daemon.cell.supervisor import MotionInterlock
from tandemscan.daemon.cli import cell_cmd
from tandemscan.daemon.cli.command import EXIT_SAFETY_STOP
from tandemscan.daemon.jobs.runner import JobRunner
from tandemscan.daemon.plans import default_plan_path
from tandemscan.drivers.errors import SafetyStop
from tandemscan.drivers.interfaces import ChassisPose
from tandemscan.pipeline.planning.plan import Plan
from tandemscan.sim_drivers.hil_box import BOX_PLAN, write_hil_box_cell


@pytest.fixture(scope="module")
def hil_toml(tmp_path_factory) -> Path:
    """config/hil-cell.toml with free ports and a 3 x 2 x 1.6 m box as the part, and the band plan for the box."""
    return write_hil_box_cell(tmp_path_factory.mktemp("hil"), default_plan_path(), "cli")


@pytest.fixture
def estop_after_two_captures(monkeypatch) -> list[CellSession]:
    """Every session the CLI opens; in each, the e-stop is pressed as the first motion after the second
    capture starts (the world's input, mirrored onto the Modbus emulator within half a control period)."""
    sessions: list[CellSession] = []
    build = cell_cmd._session

    def spied(config):
        session = build(config)
        world = session.cell.simulation.world
        start = world.motion.start

        def started(robot: str) -> None:
            start(robot)
            if world.captures >= 2 and not world.safety.estop:
                world.safety.estop = True

        world.motion.start = started
        sessions.append(session)
        return session

    monkeypatch.setattr(cell_cmd, "_session", spied)
    return sessions


def safety_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("safety stop:")]


def test_estop_during_measure_stops_motion_exits_nonzero_and_keeps_the_scans(hil_toml, estop_after_two_captures,
                                                                             tmp_path, capfd):
    status = cli.main(["measure", "--config", str(hil_toml), "--plan", str(hil_toml.parent / BOX_PLAN),
                       "--out", str(tmp_path)])
    err = capfd.readouterr().err
    assert status == EXIT_SAFETY_STOP and "Traceback" not in err
    (line,) = safety_lines(err)
    assert "e-stop pressed" in line and "scans measured so far are in" in line
    (session,) = estop_after_two_captures
    world = session.cell.simulation.world
    assert session.supervisor.latched_reason == "e-stop pressed" and not session.active
    assert world.motion.moving == set() and world.motion.violations == []
    scans = sorted(tmp_path.glob("job-*/scans/scan-*.npz"))
    assert len(scans) == world.captures >= 2  # every capture before the stop is on disk, with its reading
    for path in scans:
        with np.load(path) as scan:
            assert scan["T_C_T"].shape == (4, 4) and len(scan["points_S_mm"]) > 0
    assert not list(tmp_path.glob("job-*/report.json"))  # the job stopped: no report of a finished job


def test_estop_during_calibrate_stops_motion_and_writes_no_calibration(hil_toml, estop_after_two_captures,
                                                                       tmp_path, capfd):
    out = tmp_path / "calibration.json"
    status = cli.main(["calibrate", "--config", str(hil_toml), "--out", str(out)])
    err = capfd.readouterr().err
    assert status == EXIT_SAFETY_STOP and "Traceback" not in err
    (line,) = safety_lines(err)
    assert "e-stop pressed" in line and f"no calibration written to {out}" in line
    (session,) = estop_after_two_captures
    assert session.supervisor.latched_reason == "e-stop pressed"
    assert session.cell.simulation.world.motion.moving == set() and not out.exists()


async def test_the_gate_refuses_motion_outside_an_open_session_and_one_robot_while_another_moves(sim_config, tmp_path):
    slow = sim_config.model_copy(update={"sim": sim_config.sim.model_copy(update={"time_scale": 1.0})})
    session = CellSession(slow)
    with pytest.raises(SafetyStop, match="session is not open"):
        async with session.gate.motion(Robot.MEASURE):
            pass
    async with session:
        async def drive():  # 3 m at real speed: 10 s, cancelled below
            async with session.gate.motion(Robot.TRACKING) as robot:
                o = await robot.chassis.odometry()
                await robot.chassis.move_to(ChassisPose(o.x_mm + 3000.0, o.y_mm, o.heading_rad))

        task = asyncio.create_task(drive())
        while session.supervisor.moving_robots != [Robot.TRACKING]:
            await asyncio.sleep(0.01)
        joints = await session.cell.arm.joints()
        # the runner as `tandemscan measure` runs it: its first arm move meets the interlock
        plan = Plan.model_validate({"name": "arm", "steps": [{"kind": "move_arm", "joints_rad": joints.tolist()},
                                                            {"kind": "scan"}]})
        with pytest.raises(MotionInterlock, match="measure robot may not move while tracking robot is moving"):
            await JobRunner(session, plan, slow, tmp_path / "job").run()
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
    assert session.cell.simulation.world.motion.violations == []
