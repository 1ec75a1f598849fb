"""The whole default part: the generated plan is consistent with the simulated cell, covers what the arm
reaches, reports what it leaves out, and the CLI writes the plan, its report and the top view."""

from __future__ import annotations

import json

import numpy as np
import pytest
from tandemscan.config import load_config
from tandemscan.daemon.cli import main
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.planning.coverage import dry_run
from tandemscan.pipeline.planning.parameters import PartPlanning
from tandemscan.pipeline.planning.plan import MoveArm, MoveMeasure, MoveTracker, Plan, Scan
from tandemscan.pipeline.planning.planner import plan_part
from tandemscan.pipeline.planning.tracker import is_valid_chain
from tandemscan.sim_drivers.world import SimWorld


@pytest.fixture(scope="module")
def planned():
    config = load_config()
    world = SimWorld(config)
    start = config.sim.tracking_start
    plan = plan_part(world.mesh, PartPlanning.from_config(config),
                     tracker_start=(start.x_mm, start.y_mm, np.radians(start.heading_deg)))
    return config, world, plan


def test_tracker_chain_is_optimal_and_valid(planned):
    _, _, plan = planned
    assert plan.tracker.optimal
    assert plan.tracker.count == plan.tracker.lower_bound
    assert is_valid_chain(plan.cover, plan.tracker.chain)
    assert plan.tracker.chain[0] == plan.start_candidate  # the tracker starts where it stands
    assert plan.sequence.plan.transfer_count == plan.tracker.count - 1


def test_every_scan_and_transfer_is_seen_by_the_simulated_tracker(planned):
    """Walk the plan on the sim world without slip: the target is visible at every scan and both sides of a transfer."""
    _, world, plan = planned
    tracking, measuring = world.chassis["tracking_chassis"], world.chassis["measure_chassis"]
    scans = 0
    for step in plan.sequence.plan.steps:
        if isinstance(step, MoveTracker):
            assert world.target_visibility() is None, "target lost before the transfer"
            tracking.true_pose = F.planar_pose(step.x_mm, step.y_mm, step.heading_rad)
            assert world.target_visibility() is None, "target not seen after the transfer"
        elif isinstance(step, MoveMeasure):
            measuring.true_pose = F.planar_pose(step.x_mm, step.y_mm, step.heading_rad)
        elif isinstance(step, MoveArm):
            assert world.kinematics.within_limits(np.array(step.joints_rad))
            world.joints_rad = np.array(step.joints_rad)
        elif isinstance(step, Scan):
            assert world.target_visibility() is None, step.label
            scans += 1
            if scans % 10 == 0:  # the scanner really sees the part from here (spot checks keep the test fast)
                points, _ = world.scanner_model.scan(world.scene, world.T_F_S())
                assert len(points) > 1000, step.label
    assert scans == plan.sequence.plan.scan_count == len(plan.poses)


def test_one_robot_moves_at_a_time_and_the_arm_folds_before_driving(planned):
    _, world, plan = planned
    steps = plan.sequence.plan.steps
    home = tuple(np.radians(load_config().sim.arm_home_deg))
    for prev, step in zip(steps[:-1], steps[1:], strict=True):
        if isinstance(step, MoveMeasure) and not isinstance(prev, MoveMeasure):
            assert isinstance(prev, MoveArm) and np.allclose(prev.joints_rad, home)


def test_no_pose_is_scanned_twice(planned):
    """Two raster rows falling on one profile sample (a shallow slope) give one scan, not two of one pose."""
    steps = planned[2].sequence.plan.steps
    assert all(isinstance(a, MoveArm) for a, b in zip(steps[:-1], steps[1:], strict=True) if isinstance(b, Scan))


def test_coverage_of_the_reachable_surface_and_left_out_areas_reported(planned):
    config, world, plan = planned
    cell = PartPlanning.from_config(config)
    report = dry_run(world.mesh, world.scene, plan.rasters, cell.scanner, cell.coverage_incidence_limit_rad)
    assert report.coverage_of_reachable_pct >= 95.0
    assert report.seen_area_mm2 > 0.5 * (report.total_area_mm2 - report.floor_contact_mm2)
    # the roof of a 1.6 m part is out of the arm's reach: reported with where it is, not silently skipped
    assert report.unreachable_mm2 > 0
    unreachable = [lo for lo in report.left_out if lo.reason == "out of the arm's reach"]
    assert unreachable and max(lo.z_range_mm[1] for lo in unreachable) > 1400.0
    total = report.seen_area_mm2 + report.floor_contact_mm2 + report.unreachable_mm2 + report.missed_mm2
    assert total == pytest.approx(report.total_area_mm2, rel=1e-9)


def test_cli_plan_writes_plan_report_and_picture(tmp_path, capsys):
    out = tmp_path / "plan.toml"
    png = tmp_path / "plan.png"
    assert main(["plan", "--out", str(out), "--png", str(png)]) == 0
    plan = Plan.load(out)
    assert plan.scan_count > 100 and plan.transfer_count >= 1
    report = json.loads((tmp_path / "plan-report.json").read_text())
    assert report["tracker_optimal"] and report["coverage"]["coverage_of_reachable_pct"] >= 95.0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_plan_bad_mesh_is_one_line_error(tmp_path, capsys):
    assert main(["plan", "--part", str(tmp_path / "missing.stl"), "--out", str(tmp_path / "p.toml")]) == 2
    assert "missing.stl" in capsys.readouterr().err


def test_the_arm_starts_from_the_planning_setting(monkeypatch):
    """The first station's IK starts from ``[planning] arm_start_deg``, not from the simulator's table."""
    from tandemscan.pipeline.planning import planner

    class Seen(Exception):
        pass

    def seen(*args):
        raise Seen(args[-1])

    config = load_config()
    start = (10.0, 80.0, 5.0, 95.0, -5.0, 0.0)
    config = config.model_copy(update={"planning": config.planning.model_copy(update={"arm_start_deg": start})})
    monkeypatch.setattr(planner, "plan_arm", seen)
    with pytest.raises(Seen) as e:
        plan_part(SimWorld(config).mesh, PartPlanning.from_config(config))
    np.testing.assert_allclose(e.value.args[0], np.radians(start))


def test_the_plan_command_starts_the_tracker_chain_at_the_planning_setting(monkeypatch):
    """``tandemscan plan`` starts the chain where ``[planning] tracker_start`` puts the tracking robot."""
    from tandemscan.daemon import plans
    from tandemscan.pipeline.planning import planner

    seen = {}
    monkeypatch.setattr(planner, "plan_part", lambda mesh, config, **k: seen.update(k) or "planned")
    config = load_config()
    start = config.planning.tracker_start.model_copy(update={"x_mm": -1000.0, "heading_deg": 180.0})
    config = config.model_copy(update={"planning": config.planning.model_copy(update={"tracker_start": start})})
    assert plans.plan_configured_part(config, "p")[1] == "planned"
    np.testing.assert_allclose(seen["tracker_start"], (-1000.0, start.y_mm, np.pi))
