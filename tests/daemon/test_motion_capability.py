"""Motion as a capability (docs/architecture.md, "The motion gate"): a robot's motion commands are reachable only
through the handle ``gate.motion(Robot.X)`` hands out for one block."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest
from tandemscan.daemon.cell.motion import NoMotionCapability, Robot
from tandemscan.daemon.cell.session import CellSession
from tandemscan.drivers.interfaces import Arm, ArmReadings, ChassisPose, DeviceState


async def test_a_move_without_the_capability_never_reaches_the_device(sim_config):
    async with CellSession(sim_config) as session:
        cell, world = session.cell, session.cell.simulation.world
        q = np.asarray(world.joints_rad).copy()
        target = q + np.radians([5.0, 0, 0, 0, 0, 0])
        o = await cell.measure_chassis.odometry()
        with pytest.raises(NoMotionCapability, match=r"move_joints is not reachable here"):
            await cell.arm.move_joints(target)
        with pytest.raises(NoMotionCapability):
            await cell.measure_chassis.move_to(ChassisPose(o.x_mm + 500.0, o.y_mm, o.heading_rad))
        with pytest.raises(NoMotionCapability):
            await cell.tracking_chassis.stop()
        with pytest.raises(NoMotionCapability):  # nor through the supervisor's view of the devices
            await next(d for d in cell.devices() if d.name == "arm").move_joints(target)
        np.testing.assert_array_equal(world.joints_rad, q)
        assert world.motion.moving == set() and await cell.measure_chassis.odometry() == o
        assert isinstance(cell.arm, ArmReadings) and not isinstance(cell.arm, Arm)
        assert (await cell.arm.status()).state is DeviceState.IDLE

        async with session.gate.motion(Robot.MEASURE) as robot:
            await robot.arm.move_joints(target)
        np.testing.assert_allclose(world.joints_rad, target, atol=1e-9)
        with pytest.raises(NoMotionCapability, match="block has ended"):  # a handle kept past its block
            await robot.arm.move_joints(q)
        np.testing.assert_allclose(world.joints_rad, target, atol=1e-9)


async def test_the_gate_hands_out_the_robot_asked_for(sim_config):
    async with CellSession(sim_config) as session:
        async with session.gate.motion(Robot.TRACKING) as robot:
            assert not hasattr(robot, "arm") and robot.chassis.name == session.cell.tracking_chassis.name
        async with session.gate.motion(Robot.MEASURE) as robot:
            assert robot.lift is None and robot.arm.name == session.cell.arm.name


def test_only_the_session_reads_the_raw_movers():
    """The raw movers are a private field of the cell; its one reader is the gate in ``daemon/cell/session.py``."""
    root = Path(__file__).resolve().parents[2]
    readers = set()
    for folder in ("daemon", "pipeline", "drivers", "config", "sim_drivers"):
        for path in (root / folder).rglob("*.py"):
            tree = ast.parse(path.read_text(encoding="utf-8"))
            if any(isinstance(n, ast.Attribute) and n.attr == "_movers" for n in ast.walk(tree)):
                readers.add(path.relative_to(root).as_posix())
    assert readers == {"daemon/cell/devices.py", "daemon/cell/session.py"}
