"""A coordinate transfer over several arm poses (docs/architecture.md, "Coordinate transfers"): the estimate from
K pose pairs, the simulated arm's repeatability it must live with, the runner's transfer through the motion
gate and its journal."""

from __future__ import annotations

import asyncio

import numpy as np
import open3d as o3d
import pytest
from tandemscan.daemon.cell.motion import Robot
from tandemscan.daemon.cell.session import CellSession
from tandemscan.daemon.jobs.coordinate_transfer import camera_move, choose_transfer_poses, offset_poses, transfer_joints
from tandemscan.daemon.jobs.records import TransferRecord, record_from_json
from tandemscan.daemon.jobs.run_state import RelocalisationState, RunState, journal_records, replay_journal
from tandemscan.daemon.jobs.runner import JobRunner
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.part import train_nose_mesh
from tandemscan.pipeline.geometry.uncertainty import transfer_covariance
from tandemscan.pipeline.planning.plan import MoveArm, MoveMeasure, MoveTracker, Plan, Scan
from tandemscan.pipeline.stitching.installation import Installation
from tandemscan.sim_drivers.persist import restore_world_state, world_state
from tandemscan.sim_drivers.world import SimWorld
from test_relocalise import MemoryJournal, assert_same
from test_transfer_averaging import through_first_transfer

T_W_C_OLD = F.from_rotvec([200.0, 1500.0, -300.0], [0.1, 0.2, -0.3])
T_W_C_NEW = F.from_rotvec([3200.0, -400.0, 150.0], [0.02, -0.3, 1.2])


def _targets(rng: np.random.Generator, count: int) -> list[np.ndarray]:
    """``count`` target poses in W spread over an arm's reach (about 1 m), turned a little from each other."""
    return [F.from_rotvec(np.array([1500.0, 800.0, 900.0]) + rng.uniform(-400, 400, 3), rng.normal(0, 0.3, 3))
            for _ in range(count)]


def _noisy(T: np.ndarray, rng: np.random.Generator, sigma_mm: float, sigma_rad: float) -> np.ndarray:
    """``T`` with a reading's error: a turn about the target's origin and a shift of it (camera axes)."""
    out = F.from_rotvec(np.zeros(3), rng.normal(0, sigma_rad, 3)) @ T
    out[:3, 3] = T[:3, 3] + rng.normal(0, sigma_mm, 3)
    return out


def test_the_pose_estimate_recovers_a_known_transfer_exactly_from_noiseless_readings():
    T_W_T = _targets(np.random.default_rng(1), 5)
    before = [F.invert(T_W_C_OLD) @ T for T in T_W_T]
    after = [F.invert(T_W_C_NEW) @ T for T in T_W_T]
    C = np.diag([1e-3] * 3 + [1e-10] * 3)
    est = F.coordinate_transfer_poses(T_W_C_OLD, before, after, [C] * 5)
    d_mm, _ = F.pose_error(est.T_W_C, T_W_C_NEW)
    d_rad = np.linalg.norm(F.to_rotvec(F.invert(T_W_C_NEW) @ est.T_W_C)[1])  # arccos would blur below 1e-8
    assert d_mm < 1e-8 and d_rad < 1e-12
    np.testing.assert_allclose(est.centre_mm, np.mean([T[:3, 3] for T in T_W_T], axis=0))
    # one pair is Eq. 2 and its covariance, exactly
    one = F.coordinate_transfer_poses(T_W_C_OLD, before[:1], after[:1], [C])
    np.testing.assert_allclose(one.T_W_C, F.coordinate_transfer(T_W_C_OLD, before[0], after[0]), atol=1e-9)
    np.testing.assert_allclose(one.covariance, C, rtol=1e-9, atol=1e-20)


def test_with_noise_the_pose_estimate_beats_one_pose_and_its_covariance_holds():
    """Readings as the tracker gives them at 3-5 m (0.03 mm, 0.003 deg per axis, each pose its own still
    period): the rotation of 5 pairs over ~0.8 m beats one target's orientation, and the estimate's errors
    whiten to chi-square with 6 degrees of freedom under its covariance."""
    rng = np.random.default_rng(5)
    s_mm, s_rad = 0.03, np.radians(0.003)
    reading = np.diag([s_mm**2] * 3 + [s_rad**2] * 3)
    one_rot, many_rot, many_mm, one_mm, chi2 = [], [], [], [], []
    for _ in range(300):
        T_W_T = _targets(rng, 5)
        before = [_noisy(F.invert(T_W_C_OLD) @ T, rng, s_mm, s_rad) for T in T_W_T]
        after = [_noisy(F.invert(T_W_C_NEW) @ T, rng, s_mm, s_rad) for T in T_W_T]
        C = [transfer_covariance(T_W_C_OLD, reading, T_W_C_NEW, reading)] * 5
        est = F.coordinate_transfer_poses(T_W_C_OLD, before, after, C)
        single = F.coordinate_transfer(T_W_C_OLD, before[0], after[0])
        many_rot.append(F.pose_error(est.T_W_C, T_W_C_NEW)[1])
        one_rot.append(F.pose_error(single, T_W_C_NEW)[1])
        # the error as a world motion about the estimate's centre, whitened by its covariance
        D = est.T_W_C @ F.invert(T_W_C_NEW)
        e = np.r_[D[:3, :3] @ est.centre_mm + D[:3, 3] - est.centre_mm, F.to_rotvec(D)[1]]
        chi2.append(e @ np.linalg.solve(est.covariance, e))
        many_mm.append(np.linalg.norm(e[:3]))
        one_mm.append(np.linalg.norm((single @ F.invert(T_W_C_NEW) @ np.r_[est.centre_mm, 1])[:3] - est.centre_mm))
    rms = lambda v: float(np.sqrt(np.mean(np.square(v))))  # noqa: E731
    assert rms(many_rot) < 0.5 * rms(one_rot)
    assert rms(many_mm) < 0.6 * rms(one_mm)
    assert np.mean(chi2) == pytest.approx(6.0, rel=0.15)


def test_the_simulated_arm_lands_the_same_joints_within_its_repeatability(sim_config):
    world = SimWorld(sim_config)
    q0, q1 = world.joints_rad.copy(), world.joints_rad + np.radians([10, 5, -5, 0, 10, 0])
    sigma_mm, sigma_rad = sim_config.sim.arm_repeatability.sigma()
    assert sigma_mm == pytest.approx(0.03 / 3.6) and sigma_mm > 0  # the vendor's RP, ISO 9283
    nominal = world.T_F_E()
    flange = []
    for _ in range(300):
        world.move_arm(q1)
        world.move_arm(q0)
        flange.append(F.to_rotvec(F.invert(nominal) @ world.T_F_E()))
    shift = np.array([t for t, _ in flange])
    turn = np.array([r for _, r in flange])
    # the same joints: the flange lands about its pose by a fresh offset per move, the configured sigma per axis
    assert np.all(np.abs(np.std(shift, axis=0) / sigma_mm - 1) < 0.2)
    assert np.all(np.abs(np.std(turn, axis=0) / sigma_rad - 1) < 0.2)
    assert len({tuple(t) for t in shift.round(9)}) == len(shift)
    # a move of no travel keeps the flange where it landed
    here = world.T_F_E()
    world.move_arm(q0)
    np.testing.assert_array_equal(world.T_F_E(), here)
    # the offset is part of the world's kept state: a restored world stands where this one stands
    saved = world_state(world)
    again = SimWorld(sim_config)
    restore_world_state(again, saved)
    np.testing.assert_array_equal(again.T_F_E(), here)
    world.move_arm(q1)
    again.move_arm(q1)
    np.testing.assert_array_equal(again.T_F_E(), world.T_F_E())


@pytest.fixture
def arm_poses_config(sim_config):
    return sim_config.model_copy(update={
        "tracker": sim_config.tracker.model_copy(update={"transfer_arm_poses": 4, "transfer_samples": 3}),
        "correction": sim_config.correction.model_copy(update={"enabled": False}),
        "inspection": sim_config.inspection.model_copy(update={"in_job": False}),
        "job": sim_config.job.model_copy(update={"relocalise": False}),
    })


async def test_the_runner_carries_the_target_through_the_poses_under_the_gate_and_replays_its_journal(
        arm_poses_config, tmp_path):
    """The transfer of the shipped plan's first tracker move, at 4 arm poses: the arm moves only inside the
    measurement robot's motion gate (sampled while the simulated arm moves), the record lists the pairs, its
    prior is the estimate's, the journal replays to the same state, and a restart after the noted readings
    completes the transfer from them."""
    shipped = through_first_transfer()
    i = next(k for k, s in enumerate(shipped.steps) if isinstance(s, MoveTracker) and k > 0)
    # ending with the transfer: after the first run the robots stand where a crash after it would leave them
    plan = Plan(name="up to the first transfer", steps=shipped.steps[:i + 1])
    config = arm_poses_config.model_copy(update={"sim": arm_poses_config.sim.model_copy(update={"time_scale": 0.002})})
    samples: list[bool] = []
    async with CellSession(config) as session:
        world = session.cell.simulation.world

        async def watch() -> None:
            while True:
                if SimWorld.MEASURE_ROBOT in world.motion.moving:
                    samples.append(Robot.MEASURE in session.supervisor.moving_robots)
                await asyncio.sleep(0.0005)

        watcher = asyncio.create_task(watch())
        journal = MemoryJournal()
        runner = JobRunner(session, plan, config, tmp_path, journal=journal)
        try:
            await runner.run()
            # a restart after the readings before the tracker's move were noted: the transfer completes from them
            again = MemoryJournal({k: journal.results[k] for k in range(i)}, {i: journal.notes(i)})
            await JobRunner(session, plan, config, tmp_path, journal=again).run()
        finally:
            watcher.cancel()
            await asyncio.gather(watcher, return_exceptions=True)
        q0, _ = transfer_joints(plan, i, {})
        assert world.motion.violations == []
    assert samples and all(samples)
    record = record_from_json(plan.steps[i], journal.results[i], tmp_path)
    resumed = record_from_json(plan.steps[i], again.results[i], tmp_path)
    np.testing.assert_array_equal(resumed.before_T_C_T, record.before_T_C_T)
    assert [p["joints_rad"] for p in resumed.arm_poses] == [p["joints_rad"] for p in record.arm_poses]
    assert [p["before"] for p in resumed.arm_poses] == [p["before"] for p in record.arm_poses]
    assert F.pose_error(resumed.T_W_C, record.T_W_C)[0] < 0.5  # read again after the move: close, not equal
    assert isinstance(record, TransferRecord) and record.arm_poses_requested == 4
    assert len(record.arm_poses) >= 2, record.arm_poses_dropped
    np.testing.assert_allclose(record.arm_poses[0]["joints_rad"], q0)
    # the prior is about the targets' centroid, with the K-pose covariance (not pose 0's Eq. 2 alone)
    targets = [(record.T_W_C @ np.array(p["after"]))[:3, 3] for p in record.arm_poses]
    np.testing.assert_allclose(record.target_W_mm, np.mean(targets, axis=0), atol=0.5)
    # W is the first station's camera frame: pose 0's Eq. 2 alone would be before @ inv(after); the pairs moved it
    d_mm, _ = F.pose_error(record.T_W_C, F.coordinate_transfer(np.eye(4), record.before_T_C_T, record.after_T_C_T))
    assert d_mm > 1e-6
    assert len(journal.notes(i)["before"]["poses"]) == len(record.arm_poses) + sum(
        d["side"] == "after" for d in record.arm_poses_dropped)
    # replayed from the journal, the job's state is the one the run ended with
    records = journal_records(plan, journal.results, journal.notes, tmp_path, False)
    assert_same(replay_journal(RunState(relocalisation=RelocalisationState()), records), runner.state)


def test_a_transfer_journaled_before_arm_poses_reads_as_one_pose():
    old = {"T_W_C": np.eye(4).tolist(), "station": 1, "before": np.eye(4).tolist(), "after": np.eye(4).tolist(),
           "odometry": [0.0, 0.0, 0.0],
           "transfer": {"station": 1, "after_scan": 3, "target_W_mm": [1.0, 2.0, 3.0],
                        "covariance": np.eye(6).tolist()}}
    record = TransferRecord.from_json(old)
    assert record.arm_poses == () and record.arm_poses_requested == 1
    assert record.to_json() == old


def test_poses_out_of_reach_or_out_of_view_are_left_out_with_the_reason(sim_config):
    """Where the shipped plan's first transfer stands: the poses around the arm's are chosen spread out and seen
    from both stations; a candidate beyond the joint limits, or one whose target the tracker would see from
    behind after its move, is left out and named, and the transfer falls back to fewer poses."""
    plan = through_first_transfer()
    i = next(k for k, s in enumerate(plan.steps) if isinstance(s, MoveTracker) and k > 0)
    world = SimWorld(sim_config)
    for step in plan.steps[:i]:
        if isinstance(step, MoveArm):
            world.move_arm(np.array(step.joints_rad))
        elif isinstance(step, MoveMeasure):
            world.chassis["measure_chassis"].true_pose = F.planar_pose(step.x_mm, step.y_mm, step.heading_rad)
    q0, others = transfer_joints(plan, i, {})
    np.testing.assert_array_equal(q0, world.joints_rad)
    # where the arm stands: the committed joints of its last move (a restart), else its joints now (re-solved)
    last = max(k for k in range(i) if isinstance(plan.steps[k], MoveArm))
    np.testing.assert_array_equal(transfer_joints(plan, i, {}, q0 + 0.01)[0], q0 + 0.01)
    committed = {last: {"joints_rad": (q0 + 0.02).tolist()}}
    np.testing.assert_array_equal(transfer_joints(plan, i, committed, q0 + 0.01)[0], q0 + 0.02)
    T_C_T0 = F.invert(world.T_F_C()) @ world.T_F_T()
    odo = world.chassis["tracking_chassis"].odometry
    here = (odo.x_mm, odo.y_mm, odo.heading_rad)
    beyond = q0.copy()
    beyond[1] = np.radians(sim_config.arm.joint_max_deg[1]) + 0.5
    chosen, left_out = choose_transfer_poses(q0, [*others, beyond], T_C_T0,
                                             camera_move(world.truth, here, plan.steps[i]), 4, sim_config, world.truth)
    assert len(chosen) == 3 and all(np.max(np.abs(q - q0)) > 0 for q in chosen)
    assert {"joints_rad": beyond.tolist(), "reason": "outside the joint limits"} in left_out
    # each chosen target seen from the tracker where it stands (the part's shadow included: the truth)
    for q in chosen:
        world.move_arm(q)
        assert world.target_visibility() is None
    # the tracker turned half round: every pose's target would face away from it
    away = MoveTracker(x_mm=odo.x_mm, y_mm=odo.y_mm, heading_rad=odo.heading_rad + np.pi)
    none, left_out = choose_transfer_poses(q0, [], T_C_T0, camera_move(world.truth, here, away), 4, sim_config,
                                           world.truth)
    assert none == [] and left_out
    assert all(d["reason"] == "target predicted out of view after the move" for d in left_out)


def _world_at(world: SimWorld, plan: Plan, i: int) -> SimWorld:
    """``world`` with the robots where the plan's steps before ``i`` leave them (no slip)."""
    for step in plan.steps[:i]:
        if isinstance(step, MoveArm):
            world.move_arm(np.array(step.joints_rad))
        elif isinstance(step, MoveMeasure | MoveTracker):
            name = "measure_chassis" if isinstance(step, MoveMeasure) else "tracking_chassis"
            world.chassis[name].true_pose = F.planar_pose(step.x_mm, step.y_mm, step.heading_rad)
    return world


@pytest.mark.parametrize("planned", [True, False], ids=["a planned alternative", "no alternative planned"])
async def test_a_transfer_whose_own_pose_the_part_hides_reads_elsewhere_and_the_job_completes(
        planned, sim_config, tmp_path):
    """The nose with a post (120 mm square) standing a quarter of the way from the target to the tracker at the
    shipped plan's first transfer: the target is hidden behind the part at the transfer's own pose. The transfer
    (one arm pose, the default) reads it at the plan's alternative instead or, with none planned, with the scanner
    moved across its view from the own pose; the arm moved through the gate, the record names the hidden pose,
    and the job completes with the scan after the transfer."""
    plan = through_first_transfer()
    i = next(k for k, s in enumerate(plan.steps) if isinstance(s, MoveTracker) and k > 0)
    world = _world_at(SimWorld(sim_config), plan, i)
    target, camera = world.T_F_T()[:3, 3], world.T_F_C()[:3, 3]
    foot = target + 0.25 * (camera - target)
    post = o3d.geometry.TriangleMesh.create_box(120.0, 120.0, foot[2] + 100.0)
    post.translate([foot[0] - 60, foot[1] - 60, 0])
    o3d.io.write_triangle_mesh(str(tmp_path / "nose-post.stl"), (train_nose_mesh(sim_config.part) + post)
                               .compute_triangle_normals())
    config = sim_config.model_copy(update={
        "part": sim_config.part.model_copy(update={"mesh": tmp_path / "nose-post.stl"}),
        "correction": sim_config.correction.model_copy(update={"enabled": False}),
        "inspection": sim_config.inspection.model_copy(update={"in_job": False}),
        "tracker": sim_config.tracker.model_copy(update={"scan_read_retries": 0}),  # the post hides them for good
        "job": sim_config.job.model_copy(update={"relocalise": False})})
    hidden = _world_at(SimWorld(config), plan, i)
    assert "hidden behind the part" in hidden.target_visibility()
    q0, others = transfer_joints(plan, i, {})
    seen = []
    for q in others:
        hidden.move_arm(q)
        seen.append(hidden.target_visibility() is None)
    assert any(seen) and not all(seen)  # the post hides some of the station's other poses too
    # the planner's alternative: the station's last pose the post does not hide (not the first one tried anyway)
    alternative = max(k for k, ok in enumerate(seen) if ok)
    label = next(plan.steps[j + 1].label for j in range(i) if isinstance(plan.steps[j], MoveArm)
                 and isinstance(plan.steps[j + 1], Scan) and np.allclose(plan.steps[j].joints_rad, others[alternative]))
    if planned:
        plan.steps[i] = plan.steps[i].model_copy(update={"alternatives": (label,)})
    journal = MemoryJournal()
    async with CellSession(config) as session:
        result = await JobRunner(session, plan, config, tmp_path / "job", journal=journal).run()
        assert session.cell.simulation.world.motion.violations == []
    record = record_from_json(plan.steps[i], journal.results[i], tmp_path)
    read_at = np.array(record.arm_poses[0]["joints_rad"])
    if planned:
        np.testing.assert_allclose(read_at, others[alternative])
    else:
        around = offset_poses(q0, config, Installation.nominal(config.installation))
        assert any(np.allclose(read_at, q) for q in around)
    (own, *_) = record.arm_poses_dropped
    np.testing.assert_allclose(own["joints_rad"], q0)
    assert own["reason"].startswith("the transfer's own pose: target hidden behind the part")
    # the scans the post hides are left out as any untracked scan is; the one after the transfer is measured
    untracked = [u["step"] for u in result.report["relocalisation"]["untracked"]]
    assert result.report["scans"] == plan.scan_count - len(untracked) and len(untracked) == 2
    assert result.report["scan_log"][-1]["tracker_station"] == 1
    (entry,) = result.report["transfer_log"]
    assert entry["arm_poses"] == 1 and entry["arm_poses_left_out"][0]["reason"] == own["reason"]
