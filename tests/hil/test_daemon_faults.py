"""The daemon rides through faults (issue table of docs/daemon.md, faults): one test per fault, on the
hardware-in-the-loop cell (every device a real driver talking to its protocol emulator), the fault injected
through the emulators' fault dataclasses while a job runs.

A recoverable fault pauses the job in ``paused_fault`` with a typed reason and motion stopped; once the fault
clears, the retry policy resumes it and it completes with every scan exactly once. Each finished job is
compared with an uninterrupted run of the same plan.
"""

from __future__ import annotations

import asyncio
import json
import os
import time
from pathlib import Path

import numpy as np
import pytest
from tandemscan.config.models import CellConfig
from tandemscan.daemon.plans import default_plan_path
from tandemscan.daemon.service import Daemon
from tandemscan.drivers.interfaces import ChassisPose
from tandemscan.pipeline.planning.plan import Plan
from tandemscan.sim_drivers.fake_harvesters import core as fake_harvesters
from test_drivers_hil import box_part, hil_config  # noqa: F401 (box_part is a fixture)

#: the default plan's first two scans, its first transfer, and the scan after it (move_measure first)
PLAN_STEPS = (0, 1, 2, 3, 4, 13, 14, 15, 16)
TRANSFER_STEP = 5  # the move_tracker in the trimmed plan
SCAN_STEPS = (2, 4, 8)


def record_outcome(fault: str, **outcome: object) -> None:
    """Add a row to the fault matrix ``benchmarks/fault_matrix.py`` collects (``$TANDEMSCAN_FAULT_MATRIX``)."""
    path = os.environ.get("TANDEMSCAN_FAULT_MATRIX")
    if path:
        with open(path, "a", encoding="utf-8") as f:
            f.write(json.dumps({"fault": fault, **outcome}) + "\n")


def fault_config(part: Path) -> CellConfig:
    """The hil cell, quick to reconnect and retry, without the in-job inspection and the correction."""
    cfg = hil_config(part)
    return cfg.model_copy(update={
        "inspection": cfg.inspection.model_copy(update={"in_job": False}),
        "correction": cfg.correction.model_copy(update={"enabled": False}),
        "daemon": cfg.daemon.model_copy(update={
            "health_period_s": 0.1, "reconnect_initial_s": 0.1, "reconnect_max_s": 0.5,
            "fault_retry_attempts": 5, "fault_retry_initial_s": 0.2, "fault_retry_max_s": 1.0,
            "reserve_free_bytes": 0, "scan_bytes_estimate": 0}),
    })


def trimmed_plan() -> Plan:
    plan = Plan.load(default_plan_path())
    return plan.model_copy(update={"steps": [plan.steps[i] for i in PLAN_STEPS]})


class Cell:
    """A daemon on the hil cell and a recorder of every journaled event."""

    def __init__(self, daemon: Daemon):
        self.daemon = daemon
        self.emulators = daemon.cell.simulation.emulators.running
        self.world = daemon.cell.simulation.world
        self.events: list = []
        self.step_started: dict[int, asyncio.Event] = {}

    def record(self, ev) -> None:
        self.events.append(ev)
        if ev.kind == "progress" and ev.data.get("current_step") is not None:
            self.step_started.setdefault(ev.data["current_step"], asyncio.Event()).set()

    async def submit(self, plan: Plan) -> str:
        job, _ = await self.daemon.manager.submit(plan.name, {"plan": plan.model_dump(mode="json"), "label": None},
                                                  len(plan.steps), None, None)
        return job.id

    async def at_step(self, step: int, timeout_s: float = 60.0) -> None:
        await asyncio.wait_for(self.step_started.setdefault(step, asyncio.Event()).wait(), timeout_s)

    async def state(self, job_id: str, *states: str, timeout_s: float = 90.0):
        async with asyncio.timeout(timeout_s):
            while (job := self.daemon.manager.get(job_id)).state not in states:
                await asyncio.sleep(0.02)
        return job

    def states(self, job_id: str) -> list[str]:
        return [e.data["state"] for e in self.events if e.kind == "state" and e.job_id == job_id]

    def report(self, job_id: str) -> dict:
        return json.loads((self.daemon.store.job_dir(job_id) / "report.json").read_text())

    def assert_every_scan_once(self, job_id: str) -> None:
        scans = self.daemon.store.scans(job_id)
        assert [s.step_idx for s in scans] == list(SCAN_STEPS)
        files = sorted(p.name for p in (self.daemon.store.job_dir(job_id) / "scans").iterdir())
        assert files == [f"scan-{i:04d}.npz" for i in range(len(SCAN_STEPS))]
        assert self.report(job_id)["scans"] == len(SCAN_STEPS)


@pytest.fixture
async def cell(box_part, tmp_path):  # noqa: F811
    fake_harvesters.CAMERA.reset()
    daemon = Daemon(fault_config(box_part), tmp_path / "state", connect_timeout_s=30.0)
    await daemon.start()
    c = Cell(daemon)
    sub = daemon.bus.subscribe(maxsize=100000)

    async def pump():
        while True:
            c.record(await sub.get())

    task = asyncio.create_task(pump())
    try:
        yield c
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        sub.close()
        await daemon.close()


@pytest.fixture(scope="module")
def reference(box_part, tmp_path_factory):  # noqa: F811
    """Figures of an uninterrupted run of the trimmed plan on the hil cell."""

    async def run() -> dict:
        daemon = Daemon(fault_config(box_part), tmp_path_factory.mktemp("reference"), connect_timeout_s=30.0)
        await daemon.start()
        try:
            c = Cell(daemon)
            job_id = await c.submit(trimmed_plan())
            job = await c.state(job_id, "succeeded", "failed")
            assert job.state == "succeeded", job.error
            return c.report(job_id)
        finally:
            await daemon.close()

    return asyncio.run(run())


def assert_like_reference(report: dict, reference: dict) -> None:
    """Same scans and transfers; raw and stitched points within 10 % of the uninterrupted run's."""
    assert report["scans"] == reference["scans"] and report["transfers"] == reference["transfers"]
    for key in ("points_raw", "points_cloud"):
        assert abs(report[key] - reference[key]) <= 0.1 * reference[key], (key, report[key], reference[key])


async def ride_through(cell: Cell, step: int, inject, clear, device: str, exc: str | tuple[str, ...],
                       reference: dict) -> str:
    """Inject a fault when ``step`` starts, expect ``paused_fault`` naming ``device`` and ``exc`` (or one of
    several: a device the health poll finds down first is refused by the motion gate, ``NotConnected``), clear
    it, expect the job to complete from the committed steps with every scan once."""
    job_id = await cell.submit(trimmed_plan())
    await cell.at_step(step)
    await inject()
    t0 = time.monotonic()
    paused = await cell.state(job_id, "paused_fault", "failed", "succeeded")
    pause_s = time.monotonic() - t0
    assert paused.state == "paused_fault", (paused.state, paused.error)
    kinds = (exc,) if isinstance(exc, str) else exc
    assert any(f"device fault ({device}, {kind})" in paused.error for kind in kinds), paused.error
    assert "automatic resume" in paused.error, paused.error
    assert cell.daemon.supervisor.moving_robots == []
    done_at_fault = cell.daemon.store.steps_done(job_id)
    await clear()
    job = await cell.state(job_id, "succeeded", "failed")
    assert job.state == "succeeded", job.error
    assert job.attempts >= 2 and cell.daemon.store.steps_done(job_id) == len(PLAN_STEPS) > done_at_fault
    assert "paused_fault" in cell.states(job_id)
    cell.assert_every_scan_once(job_id)
    assert_like_reference(cell.report(job_id), reference)
    record_outcome(f"{device}: {' or '.join(kinds)}", outcome="paused_fault, resumed by the retry policy, succeeded",
                   reason=paused.error, paused_after_s=round(pause_s, 3), attempts=job.attempts,
                   scans=len(cell.daemon.store.scans(job_id)), points_cloud=cell.report(job_id)["points_cloud"],
                   reference_points_cloud=reference["points_cloud"])
    return job_id


def flip(obj: object, attr: str, on: object, off: object):
    """The inject and clear of a fault that is one flag of an emulator's fault dataclass."""

    async def inject():
        setattr(obj, attr, on)

    async def clear():
        setattr(obj, attr, off)

    return inject, clear


async def test_can_silent_during_a_transfer_pauses_and_the_transfer_completes(cell, reference):
    faults = cell.emulators["tracking_chassis"].faults
    job_id = await ride_through(cell, TRANSFER_STEP, *flip(faults, "drop_feedback_fraction", 0.95, 0.0),
                                "tracking_chassis", ("DeviceTimeout", "NotConnected"), reference)
    assert cell.daemon.store.notes(job_id, TRANSFER_STEP)["before"]["odometry"]


async def test_jaka_tcp_drop_during_an_arm_move(cell, reference):
    faults = cell.emulators["arm"].faults
    await ride_through(cell, 3, *flip(faults, "disconnect_on_move", True, False), "arm", "NotConnected", reference)


async def test_tracker_stall_during_a_scan(cell, reference):
    faults = cell.emulators["tracker"].faults
    await ride_through(cell, 4, *flip(faults, "stall", True, False), "tracker", "DeviceTimeout", reference)


async def test_tracker_occlusion_during_a_transfer(cell, reference, monkeypatch):
    """A transfer must see the still target (a scan whose view the tracker cannot see is left out, by design)."""

    async def inject():  # a person steps into the sight line
        monkeypatch.setattr(cell.world, "target_visibility", lambda: "occluded: someone in the sight line")

    async def clear():
        monkeypatch.undo()

    await ride_through(cell, TRANSFER_STEP, inject, clear, "tracker", "TargetNotVisible", reference)


async def test_scanner_timeout(cell, reference):
    await ride_through(cell, 2, *flip(fake_harvesters.CAMERA, "fetch_delay_s", 1e3, 0.0), "scanner", "DeviceTimeout",
                       reference)


async def test_tracker_tcp_drop_is_reconnected_and_health_follows(cell, reference):
    from tandemscan.daemon.api.models import Health

    await cell.daemon.session.supervisor.wait_connected(10)
    assert Health.model_validate(cell.daemon.health()).status == "ok"
    await cell.emulators["tracker"].drop_connections()
    async with asyncio.timeout(10):
        while "tracker" not in cell.daemon.supervisor.down_devices():
            await asyncio.sleep(0.01)
    health = cell.daemon.health()
    assert health["status"] == "degraded" and "tracker" in health["devices_down"]
    await cell.daemon.supervisor.wait_connected(10)
    assert cell.daemon.supervisor.health["tracker"].reconnects >= 1 and cell.daemon.health()["status"] == "ok"
    job_id = await cell.submit(trimmed_plan())
    assert (await cell.state(job_id, "succeeded", "failed")).state == "succeeded"
    assert_like_reference(cell.report(job_id), reference)
    record_outcome("tracker TCP drop", outcome="health degraded, tracker reconnected, the next job succeeded",
                   reconnects=cell.daemon.supervisor.health["tracker"].reconnects)


async def test_silent_safety_module_is_a_safety_stop_and_the_latch_resets_once_it_answers(cell, reference):
    job_id = await cell.submit(trimmed_plan())
    await cell.at_step(1)
    modbus = cell.emulators["safety"]
    modbus.faults.silent = True
    paused = await cell.state(job_id, "paused_safety", "failed", "succeeded", timeout_s=10)
    reason = cell.daemon.supervisor.latched_reason
    # the stale poll, not the request's 1 s timeout, tripped it
    assert paused.state == "paused_safety" and "safety I/O silent" in reason, reason
    await asyncio.sleep(2.0)  # silent for 2 s
    modbus.faults.silent = False
    async with asyncio.timeout(20):
        while True:  # refused while the module is down; accepted once it is reconnected and its inputs are clear
            try:
                await cell.daemon.manager.resume(job_id)
                break
            except Exception:
                await asyncio.sleep(0.1)
    job = await cell.state(job_id, "succeeded", "failed")
    assert job.state == "succeeded", job.error
    assert cell.daemon.supervisor.health["safety"].reconnects >= 1
    cell.assert_every_scan_once(job_id)
    record_outcome("Modbus module silent 2 s", outcome="safety stop latched (paused_safety), latch reset once it "
                   "answered, resumed, succeeded", reason=reason)


async def test_a_job_cancelled_mid_transfer_leaves_the_tracker_where_it_stood(cell, reference):
    tracking = cell.daemon.cell.tracking_chassis
    chassis = cell.emulators["tracking_chassis"]
    job_id = await cell.submit(trimmed_plan())
    await cell.at_step(TRANSFER_STEP)
    chassis.faults.ignore_commands = True  # the tracker stops half way: its move cannot finish
    async with asyncio.timeout(30):
        while "before" not in cell.daemon.store.notes(job_id, TRANSFER_STEP):
            await asyncio.sleep(0.01)
    await asyncio.sleep(0.2)
    chassis.faults.ignore_commands = False
    await cell.daemon.manager.cancel(job_id)
    assert cell.daemon.manager.get(job_id).state == "cancelled"
    noted = cell.daemon.store.notes(job_id, TRANSFER_STEP)["before"]["odometry"]
    odo = await tracking.odometry()
    assert np.hypot(odo.x_mm - noted[0], odo.y_mm - noted[1]) < 20.0
    nxt = await cell.submit(trimmed_plan())  # the next job finds the tracker where its plan starts
    job = await cell.state(nxt, "succeeded", "failed")
    assert job.state == "succeeded", job.error
    assert_like_reference(cell.report(nxt), reference)
    record_outcome("job cancelled mid-transfer", outcome="cancelled, tracker driven back to its station, the next "
                   "job succeeded", tracker_off_station_mm=round(float(np.hypot(odo.x_mm - noted[0],
                                                                                 odo.y_mm - noted[1])), 1))


async def test_a_job_posted_while_a_device_is_down_waits_queued_with_the_reason(cell, reference):
    tracker = cell.emulators["tracker"]
    await tracker.stop()  # the tracker is switched off: its link drops and reconnecting is refused
    async with asyncio.timeout(10):
        while "tracker" not in cell.daemon.supervisor.down_devices():
            await asyncio.sleep(0.02)
    job_id = await cell.submit(trimmed_plan())
    async with asyncio.timeout(10):
        while not (cell.daemon.manager.get(job_id).error or "").startswith("waiting for the cell"):
            await asyncio.sleep(0.02)
    job = cell.daemon.manager.get(job_id)
    assert job.state == "queued" and "tracker" in job.error
    job_waiting_reason = job.error
    stream = cell.daemon.config.tracker.stream
    await tracker.start_tcp(stream.host, stream.port)  # switched on again
    job = await cell.state(job_id, "succeeded", "failed")
    assert job.state == "succeeded" and job.attempts == 1, job.error
    assert cell.states(job_id)[:3] == ["queued", "queued", "running"]
    assert_like_reference(cell.report(job_id), reference)
    record_outcome("job posted while a device is down", outcome="queued with the reason, ran once the cell was "
                   "whole, succeeded", reason=job_waiting_reason)


async def test_every_device_event_serialises(cell):
    await cell.daemon.session.supervisor.wait_connected(10)
    for name in cell.daemon.supervisor.devices:
        await cell.daemon.supervisor.poll_device(name)
    snap = cell.daemon.supervisor.snapshot()
    json.dumps(snap, allow_nan=False)
    detail = {d["name"]: d["detail"] for d in snap["devices"]}
    assert detail["measure_chassis"]["pose"].keys() == {"x_mm", "y_mm", "heading_rad"}
    assert detail["safety"]["state"]["estop"] is False
    odo = await cell.daemon.cell.measure_chassis.odometry()
    assert isinstance(odo, ChassisPose)
    await cell.emulators["tracker"].drop_connections()  # a device event journaled while the cell runs
    async with asyncio.timeout(10):
        while not any(e.kind == "device" and e.data["name"] == "tracker" for e in cell.events):
            await asyncio.sleep(0.02)
    journaled = cell.daemon.store.events(0)
    assert {e.data["name"] for e in journaled if e.kind == "device"} >= {"tracker"}


async def test_a_restart_mid_job_on_the_hil_cell_goes_on_where_the_robots_stopped(box_part, tmp_path,  # noqa: F811
                                                                                    reference):
    """Issue 42 row 9: the hardware-in-the-loop cell keeps its world across a restart (as the twins' cell does: the
    arm where it stopped too, though its last move was shorter than the controller's status period) while the real
    drivers' odometry starts afresh, as on a real cell; the resumed job sees both, re-localises the odometry before
    any motion and completes like an uninterrupted run, every scan from the pose the plan put it at."""
    cfg = fault_config(box_part)
    state = tmp_path / "state"
    daemon = Daemon(cfg, state, connect_timeout_s=30.0)
    await daemon.start()
    try:
        job_id = await Cell(daemon).submit(trimmed_plan())
        async with asyncio.timeout(60):
            while daemon.store.steps_done(job_id) < 3:  # the first scan committed
                await asyncio.sleep(0.01)
        daemon.cell.simulation.world.safety.estop = True
        await Cell(daemon).state(job_id, "paused_safety")
        stopped = {name: c.true_pose.copy() for name, c in daemon.cell.simulation.world.chassis.items()}
        stopped_joints = daemon.cell.simulation.world.joints_rad.copy()
    finally:
        await daemon.close()
    daemon = Daemon(cfg, state, connect_timeout_s=30.0)
    await daemon.start()
    try:
        world = daemon.cell.simulation.world
        for name, pose in stopped.items():
            np.testing.assert_allclose(world.chassis[name].true_pose, pose, atol=1e-6)
        np.testing.assert_allclose(world.joints_rad, stopped_joints, atol=1e-6)
        await daemon.manager.resume(job_id)
        c = Cell(daemon)
        async with asyncio.timeout(90):  # to the end, through automatic resumes (a link lost on a loaded machine)
            while (job := daemon.manager.get(job_id)).state not in ("succeeded", "failed") and not (
                    job.state == "paused_fault" and "automatic resume" not in (job.error or "")):
                await asyncio.sleep(0.02)
        report = c.report(job_id) if job.state == "succeeded" else {}
        steps = daemon.store.committed_steps(job_id)
    finally:
        await daemon.close()
    assert job.state == "succeeded", job.error
    for k in SCAN_STEPS:  # each scan taken at the joints its arm move was committed with (read back, deg rounding)
        np.testing.assert_allclose(steps[k]["joints_rad"], steps[k - 1]["joints_rad"], atol=np.radians(0.05))
    resume = report["resumes"][0]  # the restart's (an automatic resume after a lost link may follow)
    # the odometry set back: the tracker confirmed nothing moved (where the arm moved since the last still reading,
    # the measurement AGV by Eq. 5 from each reading at the joints it was read at)
    assert "measure_chassis" in resume["chassis_off_journal"], resume
    assert "measure_chassis" in resume.get("odometry_relocalised", []), resume
    assert "arm_off_journal" not in resume or resume["arm_returned"], resume  # a move cut short: the arm back first
    assert report["scans_empty"] == reference["scans_empty"] == [], report["scans_empty"]
    assert_like_reference(report, reference)
