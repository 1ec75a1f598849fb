"""Scans whose target the tracker cannot see (issue 42 row 2), on a daemon over the simulated cell: the target is
read again before a scan is left out, too many left-out scans pause the job for the operator, and a job that left
out scans ends ``succeeded_with_gaps`` with the scans named in its state, its report and the REST resource."""

from __future__ import annotations

import asyncio
import json

import numpy as np
from job_reports import report_with_ground_truth
from tandemscan.daemon.api.models import job_body
from tandemscan.daemon.plans import default_plan_path
from tandemscan.daemon.service import Daemon
from tandemscan.pipeline.planning.plan import Plan

#: the default plan's first AGV station: move_measure, move_arm, scan, move_arm, scan
STEPS = 5
#: target readings of that station before its second scan, relocalising: the AGV located after its drive (which
#: places W in the plan's frame), the first scan
READS_BEFORE_SECOND_SCAN = 2


def station_config(sim_config, read_retries: int = 0, relocalise: bool = False):
    """The simulated cell, quick: ``read_retries`` reads of a hidden scan target 0.3 s apart, the first left-out
    scan a pause for the operator, no in-job inspection or correction."""
    return sim_config.model_copy(update={
        "tracker": sim_config.tracker.model_copy(update={"scan_read_retries": read_retries, "scan_read_retry_s": 0.3}),
        "job": sim_config.job.model_copy(update={"relocalise": relocalise, "max_scans_left_out": 0}),
        "inspection": sim_config.inspection.model_copy(update={"in_job": False}),
        "correction": sim_config.correction.model_copy(update={"enabled": False}),
    })


def first_station() -> Plan:
    plan = Plan.load(default_plan_path())
    return plan.model_copy(update={"steps": plan.steps[:STEPS]})


async def until(predicate, timeout_s: float = 60.0) -> None:
    async with asyncio.timeout(timeout_s):
        while not predicate():
            await asyncio.sleep(0.01)


async def test_a_hidden_target_is_read_again_and_the_job_states_its_gaps(tmp_path, sim_config):
    cfg, plan = station_config(sim_config, read_retries=4), first_station()
    daemon = Daemon(cfg, tmp_path / "state", connect_timeout_s=30.0)
    await daemon.start()
    try:
        world, manager, store = daemon.cell.simulation.world, daemon.manager, daemon.store
        world.block_sight("someone walking through the sight line")
        job, _ = await manager.submit("first station", {"plan": plan.model_dump(mode="json"), "label": None}, STEPS,
                                      None, None)
        await until(lambda: world.blocked_reads >= 2)  # the first scan's target hidden, and read again
        world.block_sight("a cart parked in the sight line", after_reads=1)  # gone for one reading, then back
        await until(lambda: manager.get(job.id).state != "running")
        paused = manager.get(job.id)
        assert [s.step_idx for s in store.scans(job.id)] == [2]  # the first scan measured once the person passed
        assert paused.state == "paused_fault", paused.error
        assert "step 4" in paused.error and "max_scans_left_out" in paused.error and "a cart" in paused.error
        await manager.resume(job.id)  # the operator accepts the gap: the still-hidden scan is left out
        await until(lambda: manager.get(job.id).state not in ("running", "paused_fault"))
        done = manager.get(job.id)
        body = job_body(done, store.steps_done(job.id))
        report = json.loads((store.job_dir(job.id) / "report.json").read_text())
    finally:
        await daemon.close()
    assert done.state == "succeeded_with_gaps", done.error
    assert done.error.startswith("1 of 2 scans left out") and "step 4" in done.error and "a cart" in done.error
    assert body.state == "succeeded_with_gaps" and body.figures["scans_left_out"] == 1 and "report" in body.links
    assert report["scans"] == 1 and [e["step"] for e in report["scans_left_out"]] == [4]


async def test_a_truncated_scan_found_on_resume_is_measured_again(tmp_path, sim_config):
    """Issue 42 row 4: scans carry their checksum in the journal; a resumed job finds a truncated scan file, names
    it (file, step, scan index; health and an event), takes its step back out of the journal and measures it
    again, and completes with every scan once."""
    cfg, plan = station_config(sim_config), first_station()
    state = tmp_path / "state"
    daemon = Daemon(cfg, state, connect_timeout_s=30.0)
    await daemon.start()
    try:  # the first scan measured, the job paused at the second (a hidden target: a deterministic stop)
        daemon.cell.simulation.world.block_sight("a cart parked in the sight line", after_reads=1)
        job, _ = await daemon.manager.submit("first station", {"plan": plan.model_dump(mode="json"), "label": None},
                                             STEPS, None, None)
        await until(lambda: daemon.manager.get(job.id).state == "paused_fault")
        (first,) = daemon.store.scans(job.id)
        assert first.step_idx == 2 and first.sha256 is not None
    finally:
        await daemon.close()
    damaged_file = state / "jobs" / job.id / first.file
    damaged_file.write_bytes(damaged_file.read_bytes()[: first.bytes // 2])  # truncated while the daemon was down
    daemon = Daemon(cfg, state, connect_timeout_s=30.0)  # the simulated world as it was, the cart gone
    await daemon.start()
    try:
        await daemon.manager.resume(job.id)
        await until(lambda: daemon.manager.get(job.id).state not in ("running", "paused_fault"))
        done = daemon.manager.get(job.id)
        health = daemon.health()
        scans = daemon.store.scans(job.id)
        events = [e.data for e in daemon.store.events(0, job.id) if e.kind == "scan_damaged"]
        report = json.loads((state / "jobs" / job.id / "report.json").read_text())
    finally:
        await daemon.close()
    assert done.state == "succeeded", done.error
    (entry,) = health["damaged_scans"]
    assert entry == {"job": job.id, "step": 2, "scan_index": 0, "file": "scans/scan-0000.npz",
                     "reason": f"{first.bytes // 2} bytes, {first.bytes} committed (truncated or overwritten)"}
    assert events == [entry]
    assert [s.step_idx for s in scans] == [2, 4] and [s.file for s in scans] == ["scans/scan-0000.npz",
                                                                                  "scans/scan-0001.npz"]
    assert sorted(p.name for p in (state / "jobs" / job.id / "scans").iterdir()) == ["scan-0000.npz", "scan-0001.npz"]
    assert report["scans"] == 2 and sorted(s["index"] for s in report["scan_log"]) == [0, 1]


def _moved(state_file, role: str, dx_mm: float) -> None:
    """Push ``role``'s AGV ``dx_mm`` along x in the saved simulated world (its wheels turning: the odometry too)."""
    world = json.loads(state_file.read_text())
    chassis = world["chassis"][role]
    chassis["true_pose"][0][3] += dx_mm
    chassis["odometry"][0] += dx_mm
    state_file.write_text(json.dumps(world))


async def paused_at_the_second_scan(cfg, state, reads: int):
    """A daemon on ``state`` runs the first station until its second scan's target is hidden (``reads`` readings on:
    a deterministic stop), then closes; returns the job's id and its committed steps' results."""
    daemon = Daemon(cfg, state, connect_timeout_s=30.0)
    await daemon.start()
    try:
        daemon.cell.simulation.world.block_sight("a cart parked in the sight line", after_reads=reads)
        job, _ = await daemon.manager.submit("first station", {"plan": first_station().model_dump(mode="json"),
                                                               "label": None}, STEPS, None, None)
        await until(lambda: daemon.manager.get(job.id).state == "paused_fault")
        assert [s.step_idx for s in daemon.store.scans(job.id)] == [2]
        return job.id, daemon.store.committed_steps(job.id)
    finally:
        await daemon.close()


async def resumed_after_restart(cfg, state, job_id: str):
    """A new daemon on ``state`` resumes the job to its end: the job, its committed steps' results, its report."""
    daemon = Daemon(cfg, state, connect_timeout_s=30.0)
    await daemon.start()
    try:
        await daemon.manager.resume(job_id)
        await until(lambda: daemon.manager.get(job_id).state not in ("running", "paused_fault"))
        return (daemon.manager.get(job_id), daemon.store.committed_steps(job_id),
                report_with_ground_truth(state / "jobs" / job_id))
    finally:
        await daemon.close()


async def test_a_restart_with_a_moved_agv_relocalises_it_before_moving(tmp_path, sim_config):
    """Issue 42 row 9: the measurement AGV pushed while the daemon was down is found off its journaled pose on
    resume and located by the tracker before the arm moves; the job completes as accurately as ever."""
    cfg, state = station_config(sim_config, relocalise=True), tmp_path / "state"
    job_id, _ = await paused_at_the_second_scan(cfg, state, READS_BEFORE_SECOND_SCAN)
    _moved(state / "sim_world.json", "measure_chassis", 150.0)
    done, _, report = await resumed_after_restart(cfg, state, job_id)
    assert done.state == "succeeded", done.error
    (resume,) = report["resumes"]
    off = resume["chassis_off_journal"]["measure_chassis"]
    assert set(resume["chassis_off_journal"]) == {"measure_chassis"} and abs(off["off_mm"] - 150.0) < 1.0
    assert resume["relocalised"] == "measure_chassis" and abs(resume["located"]["off_plan_mm"] - 150.0) < 30.0
    assert report["scans"] == 2
    truth = report["ground_truth"]
    # an uninterrupted run of this station stitches within 5.9 mm (the nominal mounts' error); the push unnoticed
    # would put the second scan 150 mm off
    assert truth["robots_moved_together"] == [] and truth["pose_err_mm_max"] < 10.0


def _arm_cut_short(state_file, joints_rad, odometry_start) -> None:
    """Put the arm at ``joints_rad`` in the saved simulated world (a move cut short) and the measurement AGV's
    odometry at ``odometry_start`` (x, y mm, heading rad: a real chassis driver's odometry starts afresh)."""
    world = json.loads(state_file.read_text())
    world["joints_rad"] = list(joints_rad)
    world["chassis"]["measure_chassis"]["odometry"] = list(odometry_start)
    state_file.write_text(json.dumps(world))


async def test_a_restart_with_the_arm_off_its_journaled_joints_moves_it_back_before_the_scan(tmp_path, sim_config):
    """Issue 42 row 9: the arm found after a restart halfway between two of the plan's poses (a move cut short) is
    seen off the joints the journal left it at, before anything moves; the tracker tells, from the readings at the
    joints each was taken at, that the measurement AGV did not move (only its odometry started afresh, set back);
    the arm is moved back and the scan is taken where the plan put it, not from where the arm happened to stand."""
    cfg, state = station_config(sim_config), tmp_path / "state"
    job_id, committed = await paused_at_the_second_scan(cfg, state, 1)  # its arm move committed
    journaled = np.array(committed[3]["joints_rad"])
    halfway = (np.array(first_station().steps[1].joints_rad) + journaled) / 2
    start = cfg.sim.measure_start
    _arm_cut_short(state / "sim_world.json", halfway, (start.x_mm, start.y_mm, np.radians(start.heading_deg)))
    done, committed, report = await resumed_after_restart(cfg, state, job_id)
    second_scan = committed[4]
    assert done.state == "succeeded", done.error
    (resume,) = report["resumes"]
    off = resume["arm_off_journal"]
    np.testing.assert_allclose(np.radians(off["read_back_deg"]), halfway, atol=1e-4)
    assert off["off_deg"] > 5.0 and resume["arm_returned"] and resume["odometry_relocalised"] == ["measure_chassis"]
    np.testing.assert_allclose(second_scan["joints_rad"], journaled, atol=1e-9)  # scanned where the plan put it
    assert report["scans"] == 2 and report["scans_empty"] == []
    assert report["ground_truth"]["pose_err_mm_max"] < 10.0
