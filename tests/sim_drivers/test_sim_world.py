"""The simulated cell's twins against the physics they model (docs/architecture.md, the cell layer; docs/drivers.md)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from tandemscan.daemon.cell.devices import build_cell
from tandemscan.drivers import ChassisPose, NotConnected, OutOfReach, SafetyStop, TargetNotVisible
from tandemscan.drivers.factory import ROLES
from tandemscan.pipeline.geometry import frames as F
from tandemscan.sim_drivers import stitch_score
from tandemscan.sim_drivers.stitch_score import cloud_to_mesh_distances


@pytest.fixture
async def cell(sim_config):
    """The twins themselves on one simulated world, without a session's supervisor and gate (what they model,
    not how the product moves them)."""
    simulation = build_cell(sim_config).simulation
    twins = {role: simulation.device(role) for role in ROLES}
    for d in twins.values():
        await d.connect()
    yield SimpleNamespace(simulation=simulation, **twins)
    for d in twins.values():
        await d.close()


async def _face_the_side(cell):
    """Arm pose of the shipped plan's first scan: the scanner faces the part's side at the sweet spot."""
    from tandemscan.daemon.plans import default_plan_path
    from tandemscan.pipeline.planning.plan import MoveArm, MoveMeasure, Plan

    plan = Plan.load(default_plan_path())
    move = next(s for s in plan.steps if isinstance(s, MoveMeasure))
    arm = next(s for s in plan.steps if isinstance(s, MoveArm))
    await cell.measure_chassis.move_to(ChassisPose(move.x_mm, move.y_mm, move.heading_rad))
    await cell.arm.move_joints(np.array(arm.joints_rad))


async def test_scanned_points_lie_on_the_mesh_within_the_noise(cell, monkeypatch):
    await _face_the_side(cell)
    frame = await cell.scanner.capture()
    world = cell.simulation.world
    assert len(frame.points_mm) > 10_000
    depth = frame.points_mm[:, 2]
    assert depth.min() >= 384 - 0.5 and depth.max() <= 520 + 0.5
    d = cloud_to_mesh_distances(world.scene, F.transform_points(world.T_F_S(), frame.points_mm))
    rms = np.sqrt(np.mean(d**2))
    # noise is 0.05 mm along the ray; the distance to the surface is its projection on the normal
    assert 0.03 < rms < 0.06
    monkeypatch.setattr(stitch_score, "SCORE_CHUNK", 4096)  # placed and measured chunk by chunk: the same distances
    placed = cloud_to_mesh_distances(world.scene, frame.points_mm.astype(np.float32), world.T_F_S())
    np.testing.assert_allclose(placed, d, atol=5e-4)  # the scene is float32: 0.1-0.2 um at metres from F
    assert np.all(np.sum(frame.normals * frame.points_mm, axis=1) < 0)  # normals face the scanner


async def test_tracker_noise_matches_its_model(cell):
    await _face_the_side(cell)
    world = cell.simulation.world
    T_true = F.invert(world.T_F_C()) @ world.T_F_T()
    readings = [await cell.tracker.read_pose() for _ in range(200)]
    errors = np.array([r.T_C_T[:3, 3] - T_true[:3, 3] for r in readings])
    sigma_p, _ = world.config.sim.tracker_noise.sigma(float(np.linalg.norm(T_true[:3, 3])))
    # one still period: the frames scatter by the fresh share, their mean keeps the still share
    # (tests/daemon/test_transfer_averaging.py checks the whole sigma over many still periods)
    f = world.config.tracker.still_noise_fraction
    assert np.std(errors - errors.mean(axis=0)) == pytest.approx(sigma_p * np.sqrt(1 - f), rel=0.15)
    assert np.abs(errors.mean(axis=0)).max() < 4 * sigma_p * np.sqrt(f + (1 - f) / 200)
    assert readings[0].covariance[0, 0] == pytest.approx(sigma_p**2)


async def test_tracker_raises_when_the_target_is_hidden_behind_the_part(cell):
    await _face_the_side(cell)
    # drive the tracker round to the far side of the part, looking back at it
    await cell.tracking_chassis.move_to(ChassisPose(-700.0, -4600.0, np.pi / 2))
    with pytest.raises(TargetNotVisible, match="tracker: .*(hidden|turned)"):
        await cell.tracker.read_pose()


async def test_tracker_raises_beyond_range_and_outside_the_view(cell):
    await _face_the_side(cell)
    await cell.tracking_chassis.move_to(ChassisPose(-700.0, 36000.0, -np.pi / 2))
    with pytest.raises(TargetNotVisible, match="beyond the 30 m range"):
        await cell.tracker.read_pose()
    await cell.tracking_chassis.move_to(ChassisPose(-700.0, 4600.0, 0.0))  # looking along the part
    with pytest.raises(TargetNotVisible, match="field of view"):
        await cell.tracker.read_pose()


async def test_an_agv_never_lands_exactly_where_commanded(cell):
    world = cell.simulation.world
    target = ChassisPose(-1800.0 + 2000.0, 2300.0, 0.0)
    odo = await cell.measure_chassis.move_to(target)
    assert odo == target  # closed loop on odometry: it believes it arrived
    true_xy = world.T_F_V2[:2, 3]
    miss_mm = np.linalg.norm(true_xy - (target.x_mm, target.y_mm))
    assert 0.01 < miss_mm < 2000 * 0.06  # percent-level slip on a 2 m move
    assert abs(np.arctan2(world.T_F_V2[1, 0], world.T_F_V2[0, 0])) > 1e-6


async def test_safety_stop_refuses_motion_and_arm_limits_are_enforced(cell):
    with pytest.raises(OutOfReach):
        await cell.arm.move_joints(np.radians([0, -120, 0, 0, 0, 0]))
    cell.simulation.world.safety.estop = True
    assert not (await cell.safety.read()).motion_allowed
    with pytest.raises(SafetyStop, match="e-stop"):
        await cell.measure_chassis.move_to(ChassisPose(0.0, 0.0, 0.0))
    with pytest.raises(SafetyStop):
        await cell.arm.move_joints(np.radians([0, 90, 0, 90, 0, 0]))


async def test_twins_refuse_verbs_before_connect(sim_config):
    cell = build_cell(sim_config)
    with pytest.raises(NotConnected, match="scanner"):
        await cell.scanner.capture()


def test_installation_truth_differs_from_nominal(sim_config):
    world = build_cell(sim_config).simulation.world
    for name in ("T_V1_C", "T_V2_B", "T_E_S", "T_T_S"):
        err_mm, err_rad = F.pose_error(getattr(world.truth, name), getattr(world.nominal, name))
        assert 0.1 < err_mm < 15 and 1e-4 < err_rad < 0.03
    world2 = build_cell(sim_config).simulation.world
    np.testing.assert_array_equal(world.truth.T_T_S, world2.truth.T_T_S)  # seeded: reproducible


async def test_the_twins_keep_the_world_state_and_a_new_simulation_restores_it(sim_config, tmp_path):
    """As a real cell keeps its robots where they stopped: what the twins did is in the state file after each
    move and reading, and a restarted simulation (a restarted daemon) goes on from there, observer log too."""
    from tandemscan.sim_drivers.cell import Simulation

    state = tmp_path / "sim_world.json"
    first = Simulation(sim_config, state_file=state)
    chassis, tracker = first.device("tracking_chassis"), first.device("tracker")
    for d in (chassis, tracker):
        await d.connect()
    observer = first.job_observer("job-1", resumed=False)
    o = await chassis.odometry()
    await chassis.move_to(ChassisPose(o.x_mm + 200.0, o.y_mm, o.heading_rad))
    observer.scan_measured(0)
    await tracker.read_pose()
    await chassis.move_to(ChassisPose(o.x_mm + 400.0, o.y_mm, o.heading_rad))  # a second still period: the
    await tracker.read_pose()  # tracker's still error of the period under way must be restored, not redrawn
    world = first.world
    again = Simulation(sim_config, state_file=state)
    assert not np.allclose(again.world.T_F_V1, world.T_F_V1)  # a fresh world stands at the start ...
    await again.start()  # ... until the session starts it from the saved state
    np.testing.assert_array_equal(again.world.T_F_V1, world.T_F_V1)
    np.testing.assert_array_equal(again.world.T_W_F, world.T_W_F)
    assert again.job_observer("job-1", resumed=True).scorer().T_W_S_true.keys() == {0}
    np.testing.assert_array_equal(again.world.measure_target()[0], world.measure_target()[0])  # same noise next
    await again.stop()
