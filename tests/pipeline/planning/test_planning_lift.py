"""Bigger cells by configuration: arm models as data, the lifting column (twin, runner, planner), the barrel
panel, and plans that state their part and what they leave out."""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d
import pytest
from tandemscan.config import ConfigError, load_config
from tandemscan.config.models import ArmConfig, LiftConfig
from tandemscan.daemon.cell.devices import CellBuildError, build_cell
from tandemscan.daemon.cell.motion import Robot
from tandemscan.daemon.cell.session import CellSession
from tandemscan.daemon.cli import main
from tandemscan.daemon.jobs.runner import JobError, JobRunner
from tandemscan.daemon.plans import default_plan_path
from tandemscan.drivers.errors import OutOfReach, SafetyStop
from tandemscan.drivers.interfaces import Lift
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.kinematics import ArmKinematics
from tandemscan.pipeline.geometry.part import (
    barrel_panel_mesh,
    load_part_mesh,
    part_identity,
    read_mesh_file,
    triangles_closed,
)
from tandemscan.pipeline.geometry.raycast import make_scene
from tandemscan.pipeline.planning.coverage import REASON_REACH, REASON_TRACKER, dry_run
from tandemscan.pipeline.planning.parameters import PartPlanning
from tandemscan.pipeline.planning.plan import MoveArm, MoveLift, MoveMeasure, Plan, Scan
from tandemscan.pipeline.planning.planner import plan_part
from tandemscan.pipeline.stitching.installation import Installation
from tandemscan.pipeline.stitching.relocalise import Relocaliser
from tandemscan.sim_drivers.cell import with_surveyed_mounts

LARGE_CELL = default_plan_path().parents[1] / "large-cell.example.toml"


@pytest.fixture(scope="module")
def large_config():
    return load_config(LARGE_CELL)


@pytest.fixture(scope="module")
def barrel():
    return barrel_panel_mesh()


@pytest.fixture(scope="module")
def barrel_plans(large_config, barrel):
    """The barrel panel planned on the default cell and on the shipped larger cell."""
    return (plan_part(barrel, PartPlanning.from_config(load_config())),
            plan_part(barrel, PartPlanning.from_config(large_config)))


def test_arm_models_fill_dh_and_limits_and_an_unknown_model_is_one_line(tmp_path):
    assert ArmConfig().dh_a_mm == (0.0, 360.0, 303.5, 0.0, 0.0, 0.0)  # the Zu 7 stays the default
    zu12 = ArmConfig(model="zu12")
    assert zu12.dh_a_mm[1:3] == (595.0, 571.5) and zu12.dh_d_mm[0] == 142.65
    assert ArmConfig.model_validate({"model": "zu18", "dh_d_mm": (1, 0, 0, 2, 3, 4)}).dh_d_mm == (1, 0, 0, 2, 3, 4)
    bad = tmp_path / "cell.toml"
    bad.write_text('[arm]\nmodel = "zu99"\n')
    with pytest.raises(ConfigError, match="unknown arm model 'zu99'"):
        load_config(bad)


def test_lift_heights_and_range_validation():
    assert LiftConfig().heights_mm() == (0.0,)
    assert LiftConfig(enabled=True, min_mm=100, max_mm=600, planning_step_mm=250).heights_mm() == (100.0, 350.0, 600.0)
    assert LiftConfig(enabled=True, min_mm=100, max_mm=600, planning_step_mm=200).heights_mm() == (
        100.0, pytest.approx(266.667, abs=1e-3), pytest.approx(433.333, abs=1e-3), 600.0)
    with pytest.raises(ValueError, match="below min_mm"):
        LiftConfig(enabled=True, min_mm=500, max_mm=100)


def test_barrel_panel_is_closed_with_its_crown_and_floor_width(barrel):
    v = np.asarray(barrel.vertices)
    assert triangles_closed(np.asarray(barrel.triangles))
    assert v[:, 2].max() == pytest.approx(1600.0) and v[:, 2].min() == 0.0
    assert v[:, 1].max() == pytest.approx(np.sqrt(2200.0**2 - 600.0**2), rel=1e-9)
    assert np.ptp(v[:, 0]) == pytest.approx(4000.0)


async def test_lift_twin_raises_the_arm_refuses_out_of_range_and_stops_on_the_latch(large_config):
    async with CellSession(large_config) as session:
        cell, world = session.cell, session.cell.simulation.world
        assert cell.lift.name in [d.name for d in cell.devices()]
        assert cell.lift.name in [d.name for d in cell.motion_devices()[Robot.MEASURE]]
        before = world.T_F_S().copy()
        async with session.gate.motion(Robot.MEASURE) as robot:
            assert isinstance(robot.lift, Lift) and not isinstance(cell.lift, Lift)
            assert await robot.lift.move_to(400.0) == 400.0 == await cell.lift.height()
            assert world.T_F_S()[:3, 3] - before[:3, 3] == pytest.approx([0.0, 0.0, 400.0])
            with pytest.raises(OutOfReach, match="outside 0 .. 1000 mm"):
                await robot.lift.move_to(1200.0)
        world.safety.estop = True
        with pytest.raises(SafetyStop):
            async with session.gate.motion(Robot.MEASURE) as robot:
                await robot.lift.move_to(100.0)
        assert await cell.lift.height() == 400.0 and not world.motion.violations
    assert build_cell(load_config()).lift is None


def test_a_real_lifting_column_is_refused_until_a_driver_exists(large_config):
    real = large_config.model_copy(update={"lift": large_config.lift.model_copy(update={"driver": "real"})})
    with pytest.raises(CellBuildError, match="lift: no driver 'real' registered"):
        build_cell(real)


def test_relocaliser_locates_the_agv_with_the_column_raised(large_config):
    """Eq. 5 with the column: the AGV pose from a (noise-free) target pose and the joints, column height known."""
    inst = Installation.nominal(large_config.installation)
    reloc = Relocaliser(large_config.arm, large_config.scanner, inst)
    q = np.radians([10.0, 100.0, -20.0, 80.0, 30.0, 5.0])
    T_F_V2 = F.planar_pose(1200.0, -300.0, 0.4)
    T_F_T = T_F_V2 @ F.compose(inst.T_V2_B, F.from_rotvec([0.0, 0.0, 650.0], np.zeros(3)),
                               ArmKinematics(large_config.arm).forward(q), inst.T_E_T)
    assert np.allclose(reloc.agv_in_world(T_F_T, q, 650.0), T_F_V2, atol=1e-9)
    assert not np.allclose(reloc.agv_in_world(T_F_T, q, 0.0), T_F_V2, atol=1.0)


async def test_runner_moves_the_column_in_the_gate_and_scans_from_the_raised_arm(sim_config, tmp_path):
    config = sim_config.model_copy(update={
        "lift": LiftConfig(enabled=True, max_mm=1000.0),
        "correction": sim_config.correction.model_copy(update={"enabled": False}),
        "inspection": sim_config.inspection.model_copy(update={"in_job": False}),
        "job": sim_config.job.model_copy(update={"relocalise": False})})
    band = Plan.load(default_plan_path()).steps  # its first station and scan pose, seen from the tracker's start
    drive, pose = next(s for s in band if isinstance(s, MoveMeasure)), next(s for s in band if isinstance(s, MoveArm))
    plan = Plan(name="lift", steps=[drive, MoveLift(height_mm=300.0), pose, Scan(label="raised")])
    async with CellSession(config) as session:
        world = session.cell.simulation.world
        config = with_surveyed_mounts(config, session.cell.simulation, tmp_path)
        result = await JobRunner(session, plan, config, tmp_path / "job").run()
        assert world.lift_mm == 300.0 and result.report["scans"] == 1 and not result.report["scans_empty"]
        assert result.report["ground_truth"]["cloud_rms_mm"] < 0.2
        raised = world.T_F_S()[:3, 3]
        world.lift_mm = 0.0
        assert raised - world.T_F_S()[:3, 3] == pytest.approx([0.0, 0.0, 300.0])  # scanned from up there
        assert not result.report["ground_truth"]["robots_moved_together"]
    async with CellSession(load_config()) as no_lift:
        with pytest.raises(JobError, match="has none"):
            await JobRunner(no_lift, plan, load_config(), tmp_path / "job2").run()


@pytest.mark.slow
def test_larger_cell_covers_the_barrel_with_column_moves_while_the_arm_is_folded(barrel_plans, large_config):
    small, large = barrel_plans
    assert large.coverage.coverage_pct >= 95.0 > small.coverage.coverage_pct
    steps = large.sequence.plan.steps
    lifts = [s for s in steps if isinstance(s, MoveLift)]
    assert lifts and all(large_config.lift.min_mm <= s.height_mm <= large_config.lift.max_mm for s in lifts)
    assert len({s.height_mm for s in lifts}) > 1
    home = tuple(np.radians(large_config.sim.arm_home_deg))
    for prev, step in zip(steps[:-1], steps[1:], strict=True):
        if isinstance(step, (MoveLift, MoveMeasure)) and not isinstance(prev, (MoveLift, MoveMeasure)):
            assert isinstance(prev, MoveArm) and np.allclose(prev.joints_rad, home)
    assert not any(isinstance(s, MoveLift) for s in small.sequence.plan.steps)


@pytest.mark.slow
def test_plan_states_its_part_and_every_area_it_leaves_out(barrel_plans, barrel):
    small, _ = barrel_plans
    plan = small.sequence.plan
    assert plan.part_identity == part_identity(barrel)
    assert plan.part_identity.bbox_max_mm[2] == pytest.approx(1600.0)
    cov = small.coverage
    assert [a.model_dump() for a in plan.left_out] == [a.model_dump() for a in cov.left_out_areas()]
    unseen = cov.total_area_mm2 - cov.seen_area_mm2
    assert sum(lo.area_mm2 for lo in cov.left_out) == pytest.approx(unseen, rel=1e-9)
    crown = [lo for lo in cov.left_out if lo.reason == REASON_REACH and lo.z_range_mm[1] > 1500.0]
    assert crown and sum(lo.area_mm2 for lo in crown) > 1e6  # the default cell does not reach the crown


@pytest.mark.slow
def test_poses_no_tracker_station_sees_are_reported_as_outside_its_view(barrel_plans, barrel):
    plan = barrel_plans[0]
    poses = [p for r in plan.rasters for p in r.poses]
    tracked = np.ones(len(poses), bool)
    tracked[: len(poses) // 2] = False
    report = dry_run(barrel, make_scene(barrel), plan.rasters, PartPlanning.from_config(load_config()).scanner,
                     np.radians(45.0), tracked)
    assert report.untracked_mm2 > 1e6 and report.seen_area_mm2 < plan.coverage.seen_area_mm2
    assert {lo.reason for lo in report.left_out} >= {REASON_TRACKER, REASON_REACH}


def test_measure_refuses_a_plan_made_for_another_part(tmp_path, barrel, capsys):
    panel = tmp_path / "panel.ply"
    o3d.io.write_triangle_mesh(str(panel), barrel)
    assert main(["measure", "--part", str(panel), "--plan", str(default_plan_path())]) == 2
    err = capsys.readouterr().err.strip()
    assert "plan made for another part" in err and "panel.ply" in err and len(err.splitlines()) == 1
    assert part_identity(load_part_mesh(load_config().part)) == Plan.load(default_plan_path()).part_identity


@pytest.mark.slow
def test_measure_part_without_a_plan_plans_that_part_and_says_so(tmp_path, capsys):
    box = o3d.geometry.TriangleMesh.create_box(900.0, 600.0, 500.0).translate((-450.0, -300.0, 0.0))
    part = tmp_path / "box.ply"
    o3d.io.write_triangle_mesh(str(part), box)
    cell = tmp_path / "cell.toml"
    cell.write_text("[correction]\nenabled = false\n[inspection]\nin_job = false\n")
    assert main(["measure", "--config", str(cell), "--part", str(part), "--out", str(tmp_path / "out")]) == 0
    said = capsys.readouterr()
    assert "no --plan given: planned" in said.err
    (job_dir,) = (tmp_path / "out").iterdir()
    plan = Plan.load(job_dir / "plan.toml")
    assert plan.part == str(part) and plan.part_identity == part_identity(read_mesh_file(part))
    report = json.loads((job_dir / "report.json").read_text())
    assert report["scans_planned"] == plan.scan_count > 10 and report["scans"] > 0.9 * plan.scan_count
    # the plan's coverage in report.json and the summary; measured unknown: no inspection aligned the cloud
    assert report["coverage"]["planned_pct"] == plan.coverage_pct > 50 and report["coverage"]["measured_pct"] is None
    assert (f"coverage of the surface where a pose fits: planned {plan.coverage_pct:.1f} %, measured unknown"
            in said.out)


async def test_a_scan_whose_target_the_tracker_cannot_see_is_left_out_and_reported(sim_config, tmp_path):
    config = sim_config.model_copy(update={
        "tracker": sim_config.tracker.model_copy(update={"scan_read_retries": 0}),  # turned away for good
        "correction": sim_config.correction.model_copy(update={"enabled": False}),
        "inspection": sim_config.inspection.model_copy(update={"in_job": False}),
        "job": sim_config.job.model_copy(update={"relocalise": False})})
    band = Plan.load(default_plan_path()).steps
    drive, pose = next(s for s in band if isinstance(s, MoveMeasure)), next(s for s in band if isinstance(s, MoveArm))
    away = np.array(pose.joints_rad) + np.radians([180.0, 0, 0, 0, 0, 0])  # the target turned from the camera
    plan = Plan(name="hidden", steps=[drive, pose, Scan(label="seen"), MoveArm(joints_rad=tuple(away)),
                                      Scan(label="hidden"), pose, Scan(label="seen again")])
    async with CellSession(config) as session:
        report = (await JobRunner(session, plan, config, tmp_path / "job").run()).report
    assert report["scans"] == 2 and report["scans_planned"] == 3
    (entry,) = report["relocalisation"]["untracked"]
    assert entry["label"] == "hidden" and "turned" in entry["reason"]
    assert report["relocalisation"]["untracked_count"] == 1


async def test_the_supervisor_halts_the_column_with_the_measurement_robot(large_config):
    from tandemscan.daemon.cell.devices import Cell
    from tandemscan.drivers.factory import ROLES
    from tandemscan.drivers.interfaces import DeviceState
    from tandemscan.sim_drivers.cell import Simulation

    simulation = Simulation(large_config)
    twins = {role: simulation.device(role) for role in (*ROLES, "lift")}  # the test holds the column's twin
    async with CellSession(large_config, cell=Cell(**twins, simulation=simulation)) as session:
        cell, supervisor = session.cell, session.supervisor
        assert cell.lift.name in [d.name for d in supervisor.robots[Robot.MEASURE]]
        twins["lift"]._state = DeviceState.MOVING
        await supervisor.halt()
        assert (await cell.lift.status()).state == DeviceState.IDLE
