"""The hardware-in-the-loop cell: real drivers built from the config, talking to emulators that move the world."""

from __future__ import annotations

import asyncio
import math
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from tandemscan.config import load_config
from tandemscan.config.loader import default_config_path
from tandemscan.config.models import CellConfig
from tandemscan.daemon.cell.devices import build_cell
from tandemscan.daemon.cell.motion import Robot
from tandemscan.daemon.cell.session import CellSession, DevicesNotConnected
from tandemscan.drivers import ChassisPose
from tandemscan.drivers.agv_can import AgvCanChassis
from tandemscan.drivers.factory import ROLES, build_real_device
from tandemscan.drivers.jaka_tcp import JakaTcpArm
from tandemscan.drivers.metronor import MetronorTracker
from tandemscan.drivers.phoxi import PhoxiScanner
from tandemscan.drivers.safety_modbus import ModbusSafetyIO
from tandemscan.pipeline.geometry import frames as F
from tandemscan.sim_drivers.emulators.agv_can import SkidSteerBody
from tandemscan.sim_drivers.hil import HilEmulators
from tandemscan.sim_drivers.hil_box import free_port
from tandemscan.sim_drivers.persist import load_world_state, save_world_state
from tandemscan.sim_drivers.world import SimWorld


@pytest.fixture(scope="module")
def box_part(tmp_path_factory) -> Path:
    """A 3 x 2 x 1.6 m box as the part (mm, floor z = 0, centred): the world builds in a second, not the nose's
    tens of seconds on a loaded machine."""
    mesh = o3d.geometry.TriangleMesh.create_box(3000.0, 2000.0, 1600.0).translate((-1500.0, -1000.0, 0.0))
    path = tmp_path_factory.mktemp("part") / "box.stl"
    mesh.compute_triangle_normals()
    o3d.io.write_triangle_mesh(str(path), mesh)
    return path


def hil_config(part_mesh: Path) -> CellConfig:
    """The shipped hil-cell.toml with free ports, so that tests never collide with a running cell."""
    cfg = load_config(default_config_path().parent / "hil-cell.toml")

    def section(name: str, sub: str, **update):
        s = getattr(cfg, name)
        return s.model_copy(update={sub: getattr(s, sub).model_copy(update=update)})

    return cfg.model_copy(update={
        "part": cfg.part.model_copy(update={"mesh": part_mesh}),
        "arm": section("arm", "jaka", command_port=free_port(), status_port=free_port()),
        "tracker": section("tracker", "stream", port=free_port()),
        "safety": section("safety", "modbus", port=free_port()),
        "measure_chassis": section("measure_chassis", "can", channel=f"hil-m-{free_port()}"),
        "tracking_chassis": section("tracking_chassis", "can", channel=f"hil-t-{free_port()}"),
    })


def test_factory_builds_every_real_driver_named_by_role():
    cfg = load_config(default_config_path().parent / "cell.example.toml")  # every role: driver = "real"
    kinds = {role: type(build_real_device(role, cfg)) for role in ROLES}
    assert kinds == {"measure_chassis": AgvCanChassis, "tracking_chassis": AgvCanChassis, "arm": JakaTcpArm,
                     "scanner": PhoxiScanner, "tracker": MetronorTracker, "safety": ModbusSafetyIO}
    assert build_real_device("tracking_chassis", cfg).name == "tracking_chassis"
    with pytest.raises(ValueError, match="unknown device role"):
        build_real_device("gripper", cfg)


def test_shipped_cell_configs_load():
    folder = default_config_path().parent
    example = load_config(folder / "cell.example.toml")
    assert all(getattr(example, role).driver == "real" for role in ROLES)
    assert not example.hil.enabled
    hil = load_config(folder / "hil-cell.toml")
    assert hil.hil.enabled and hil.scanner.phoxi.producer_path.is_file()
    sim = load_config()
    assert all(getattr(sim, role).driver == "sim" for role in ROLES) and not sim.hil.enabled


def test_mixed_cell_keeps_twins_for_sim_roles(box_part):
    cfg = load_config()
    cfg = cfg.model_copy(update={"safety": cfg.safety.model_copy(update={"driver": "real"}),
                                 "part": cfg.part.model_copy(update={"mesh": box_part})})
    cell = build_cell(cfg)
    assert isinstance(cell.safety, ModbusSafetyIO) and "SimArm" in repr(cell.arm)
    assert cell.simulation.world is not None and cell.simulation.emulators is None


async def test_hil_cell_moves_the_world_through_real_transports(box_part):
    session = CellSession(hil_config(box_part), connect_timeout_s=30.0)
    cell, world = session.cell, session.cell.simulation.world
    await session.open()
    try:
        # chassis: odometry starts at the simulated start pose and the world's chassis follows the emulator
        start = await cell.measure_chassis.odometry()
        assert (start.x_mm, start.y_mm) == (world.config.sim.measure_start.x_mm, world.config.sim.measure_start.y_mm)
        target = ChassisPose(start.x_mm + 150.0, start.y_mm, start.heading_rad)
        async with session.gate.motion(Robot.MEASURE) as robot:
            arrived = await robot.chassis.move_to(target, timeout_s=30.0)
        assert math.hypot(arrived.x_mm - target.x_mm, arrived.y_mm - target.y_mm) <= 5.0
        true_xy = world.T_F_V2[:2, 3]
        assert 100.0 < true_xy[0] - start.x_mm < 200.0  # moved, with slip
        # arm: the world's joints follow the controller
        q = world.joints_rad + np.radians([5.0, -3.0, 4.0, 0.0, 2.0, 0.0])
        async with session.gate.motion(Robot.MEASURE) as robot:
            await robot.arm.enable()
            await robot.arm.move_joints(q, timeout_s=10.0)
        np.testing.assert_allclose(world.joints_rad, q, atol=1e-9)
        np.testing.assert_allclose(await cell.arm.flange_pose(), world.kinematics.forward(q), atol=1e-6)
        # scanner: the world's ray-cast scan through the GenTL-style buffer
        captures = world.captures
        frame = await cell.scanner.capture(timeout_s=5.0)
        assert world.captures == captures + 1 and frame.points_mm.ndim == 2
        # safety: the world's e-stop reaches the driver over Modbus
        assert (await cell.safety.read()).motion_allowed
        assert not world.motion.violations
    finally:
        await session.close()


async def test_hil_tracker_and_safety_read_the_world(box_part):
    session = CellSession(hil_config(box_part), connect_timeout_s=30.0)
    cell, world = session.cell, session.cell.simulation.world
    await session.open()
    try:
        assert world.target_visibility() is None  # the default start: the tracker sees the target
        reading = await cell.tracker.read_pose(timeout_s=2.0)
        truth = F.invert(world.T_F_C()) @ world.T_F_T()
        assert F.pose_error(reading.T_C_T, truth)[0] < 0.5  # mm: tracker noise only
        world.safety.estop = True  # and the world's e-stop reaches the safety driver over Modbus
        async with asyncio.timeout(10):  # only against a hang: the next poll brings it, however loaded the machine
            while (await cell.safety.read()).motion_allowed:
                await asyncio.sleep(0.01)
        assert (await cell.safety.read()).estop
    finally:
        await session.close()


async def test_failed_connect_closes_everything(box_part):
    cfg = hil_config(box_part)
    cfg = cfg.model_copy(update={"scanner": cfg.scanner.model_copy(
        update={"phoxi": cfg.scanner.phoxi.model_copy(update={"harvesters_module": "no_such_module"})})})
    session = CellSession(cfg, connect_timeout_s=1.0)
    cell = session.cell
    with pytest.raises(DevicesNotConnected, match="not connected: scanner .*no_such_module"):
        await session.open()
    assert not cell.simulation.emulators.running
    assert not (await cell.arm.status()).connected


async def test_a_job_on_the_hil_cell_needs_no_ground_truth_and_is_inspected(box_part, tmp_path):
    """Every device a real driver: the product path alone, no observer; the inspection registers W to CAD from the
    job's own anchor reading by a best fit to the configured CAD and reports its verdict."""
    from tandemscan.daemon.jobs.runner import JobRunner
    from tandemscan.daemon.plans import default_plan_path
    from tandemscan.pipeline.planning.plan import Plan, Scan

    cfg = hil_config(box_part)
    cfg = cfg.model_copy(update={
        "correction": cfg.correction.model_copy(update={"enabled": False}),
        "inspection": cfg.inspection.model_copy(update={"views": ("isometric",), "map_width_px": 300})})
    plan = Plan.load(default_plan_path())
    scans = [i for i, s in enumerate(plan.steps) if isinstance(s, Scan)]
    plan = plan.model_copy(update={"steps": plan.steps[: scans[1] + 1]})
    async with CellSession(cfg, connect_timeout_s=30.0) as session:
        assert session.job_observer("job") is None
        with pytest.raises(ValueError, match="real drivers"):
            session.cell.simulation.write_survey(tmp_path / "survey.json")
        result = await JobRunner(session, plan, cfg, tmp_path / "job").run()
    report = result.report
    assert "ground_truth" not in report and report["scans"] == 2 and report["installation_source"] == "nominal"
    assert report["relocalisation"]["anchor"]["placed"] and (tmp_path / "job" / "report.html").is_file()
    ins = report["inspection"]
    assert "as_measured" in ins and ins["alignment"]["method"] == "best-fit" and ins["alignment"]["converged"]
    assert ins["T_F_W"] != ins["T_F_W_anchor"]
    # nominal mounts: the verdict is the decision rule's, and the report says the cell was not calibrated
    proven_out = any(a["decision"] == "nonconforming" for a in ins["deviations"])
    assert ins["verdict"] == ("fail" if proven_out else "indeterminate")
    assert ins["installation"]["source"] == "nominal" and any("nominal mounts" in r for r in ins["verdict_reasons"])


async def test_the_daemon_on_the_hil_cell_starts_its_emulators(box_part, tmp_path):
    from tandemscan.daemon.service import Daemon

    daemon = Daemon(hil_config(box_part), tmp_path / "state", connect_timeout_s=30.0)
    await daemon.start()
    try:
        assert daemon.supervisor.all_connected
        assert set(daemon.cell.simulation.emulators.running) == {"arm", "measure_chassis", "tracking_chassis",
                                                                  "tracker", "safety"}
    finally:
        await daemon.close()
    assert not daemon.cell.simulation.emulators.running



async def test_the_hil_chassis_slip_goes_on_across_a_restart_not_replayed(box_part, tmp_path):
    """An emulated chassis draws its slip from a stream the world keeps with its state (``sim_drivers.persist``): a
    restarted daemon's chassis goes on with that stream, as the twins do, instead of drawing its first moves' slip
    again after every restart; its encoders keep the same scale error."""
    cfg = hil_config(box_part)

    async def emulated_body(world: SimWorld) -> SkidSteerBody:
        emulators = HilEmulators(cfg, world)
        await emulators.start()
        body = emulators.running["measure_chassis"].body
        await emulators.stop()
        return body

    def drive(body: SkidSteerBody) -> float:
        """One move from standstill, 1 s at 500 mm/s: the distance travelled (mm)."""
        x, y = body.x_mm, body.y_mm
        body.step(500.0, 0.0, 1.0)
        body.step(0.0, 0.0, 0.0)
        return math.hypot(body.x_mm - x, body.y_mm - y)

    world = SimWorld(cfg)
    body = await emulated_body(world)
    first = drive(body)
    save_world_state(world, tmp_path / "world.json")  # as the cell saves it with the chassis at rest
    restarted = SimWorld(cfg)
    assert load_world_state(restarted, tmp_path / "world.json")
    body_after = await emulated_body(restarted)
    after_restart, uninterrupted = drive(body_after), drive(body)
    assert after_restart == pytest.approx(uninterrupted, rel=1e-12)  # the stream goes on
    assert abs(after_restart - first) > 1e-3  # not the first move's slip again (1 % sigma: about 5 mm)
    assert body_after.odometry_scale == body.odometry_scale
