"""AGV drift on the simulated cell: the runner measures where the measurement AGV stands after each drive
(Eq. 5) and re-solves the arm for the plan's scanner poses; what it cannot re-solve is reported. A plan that
opens with a tracker move relocates it without a transfer. The plan format carries the scanner poses."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from pydantic import ValidationError
from tandemscan.config import load_config
from tandemscan.daemon.cell.session import CellSession
from tandemscan.daemon.jobs.context import JobContext
from tandemscan.daemon.jobs.journal import StoreJournal
from tandemscan.daemon.jobs.manager import JobManager
from tandemscan.daemon.jobs.run_state import (
    RelocalisationState,
    RunState,
    journal_records,
    opens_with_anchor,
    replay_journal,
)
from tandemscan.daemon.jobs.runner import JobRunner
from tandemscan.daemon.store.events import EventBus
from tandemscan.daemon.store.job_store import JobStore
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.planning.parameters import PartPlanning
from tandemscan.pipeline.planning.plan import MoveArm, MoveMeasure, MoveTracker, Plan, Scan
from tandemscan.pipeline.planning.planner import plan_part
from tandemscan.pipeline.stitching.relocalise import Relocaliser, nearby_views
from tandemscan.sim_drivers.cell import with_surveyed_mounts
from tandemscan.sim_drivers.world import SimWorld


@pytest.fixture(scope="module")
def generated():
    """The generated plan of the default part (what ``make measure`` runs)."""
    config = load_config()
    start = config.sim.tracking_start
    world = SimWorld(config)
    return plan_part(world.mesh, PartPlanning.from_config(config),
                     tracker_start=(start.x_mm, start.y_mm, np.radians(start.heading_deg)))


@pytest.fixture
def drifting(sim_config):
    """The sim cell, tracker-only stitch, with a chassis that slips five times as much as the default: a few
    stations then drift as far as the whole part's 16 do by its far side (about 0.1 m)."""
    slip = sim_config.sim.measure_chassis_slip.model_copy(update={"slip_distance_fraction": 0.05,
                                                                  "slip_heading_deg": 2.0})
    return sim_config.model_copy(update={
        "sim": sim_config.sim.model_copy(update={"measure_chassis_slip": slip}),
        "correction": sim_config.correction.model_copy(update={"enabled": False}),
        "inspection": sim_config.inspection.model_copy(update={"in_job": False}),
    })


def first_scan_per_station(plan: Plan, stations: int) -> Plan:
    """The plan's first ``stations`` AGV stations (at most those the first tracker station sees), one scan at
    each."""
    steps, seen, want_scan = [], 0, False
    for step in plan.steps:
        if isinstance(step, MoveTracker) or (isinstance(step, MoveMeasure) and seen == stations):
            break
        if isinstance(step, MoveMeasure):
            seen += 1
            want_scan = True
            steps.append(step)
        elif isinstance(step, MoveArm) and (step.T_F_S is None or want_scan):
            steps.append(step)  # the fold before a drive, or the station's first scan pose
        elif isinstance(step, Scan) and want_scan:
            steps.append(step)
            want_scan = False
    last_scan = max(i for i, step in enumerate(steps) if isinstance(step, Scan))
    return Plan(name=f"{stations} stations", steps=steps[: last_scan + 1])


async def run(config, plan, job_dir, relocalise=True):
    config = config.model_copy(update={"job": config.job.model_copy(update={"relocalise": relocalise})})
    async with CellSession(config) as session:
        config = with_surveyed_mounts(config, session.cell.simulation, job_dir)
        return await JobRunner(session, plan, config, job_dir).run(), session.cell.simulation.world


def test_plan_carries_scanner_poses_and_old_plans_still_load(generated, tmp_path):
    plan = generated.sequence.plan
    home = tuple(np.radians(load_config().sim.arm_home_deg))
    moves = [s for s in plan.steps if isinstance(s, MoveArm) and not np.allclose(s.joints_rad, home)]
    assert moves and all(s.T_F_S is not None for s in moves)  # every scan pose says where the scanner should be
    assert all(s.T_F_S is None for s in plan.steps if isinstance(s, MoveArm) and s not in moves)  # folds do not
    path = tmp_path / "plan.toml"
    plan.save(path)
    again = Plan.load(path)
    assert again == plan
    old = Plan(name="old", steps=[MoveArm(joints_rad=(0.0,) * 6), Scan()])
    old.save(path)
    assert "T_F_S" not in path.read_text() and Plan.load(path).steps[0].T_F_S is None
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(ValidationError, match="rigid"):
        MoveArm(joints_rad=(0.0,) * 6, T_F_S=tuple(map(tuple, bad.tolist())))


def test_eq5_recovers_the_true_agv_pose_and_the_resolved_joints_reach_the_planned_scanner_pose(generated,
                                                                                                 sim_config):
    world = SimWorld(sim_config)
    measuring = world.chassis["measure_chassis"]
    station = generated.layout.stations[0]
    measuring.true_pose = F.planar_pose(station.x_mm + 37.0, station.y_mm - 21.0, station.heading_rad + 0.014)
    world.joints_rad = generated.poses[0].joints_rad
    reloc = Relocaliser(sim_config.arm, sim_config.scanner, world.truth)
    T_W_T = world.T_W_F @ world.T_F_T()
    T_F_V2 = F.invert(world.T_W_F) @ reloc.agv_in_world(T_W_T, world.joints_rad)
    np.testing.assert_allclose(T_F_V2, world.T_F_V2, atol=1e-6)
    target = world.T_F_S()
    measuring.true_pose = measuring.true_pose @ F.planar_pose(-15.0, 25.0, np.radians(-0.5))
    q = reloc.joints_for(world.T_F_V2, target, world.joints_rad)
    world.joints_rad = q
    err_mm, err_rad = F.pose_error(world.T_F_S(), target)
    assert err_mm < 1e-3 and err_rad < 1e-6
    far = target.copy()
    far[:3, 3] += [0.0, 0.0, 3000.0]
    assert reloc.joints_for(world.T_F_V2, far, world.joints_rad) is None


def test_nearby_views_look_at_the_same_surface_point(generated):
    T = generated.poses[0].T_F_S
    point = T @ np.array([0.0, 0.0, 442.0, 1.0])
    views = nearby_views(T, 442.0)
    assert len({what for what, _ in views}) == len(views) > 4
    for what, V in views:
        along = F.invert(V) @ point  # the planned point in the new scanner frame: on the view axis
        np.testing.assert_allclose(along[:2], 0.0, atol=1e-6)
        assert 400.0 <= along[2] <= 484.0, what
        assert np.degrees(np.arccos(np.clip(V[:3, 2] @ T[:3, 2], -1, 1))) <= 10.0 + 1e-9, what


@pytest.mark.slow
async def test_drifting_agv_loses_scans_without_relocalisation_and_none_with_it(generated, drifting, tmp_path):
    plan = first_scan_per_station(generated.sequence.plan, 6)
    assert plan.scan_count >= 4
    old, _ = await run(drifting, plan, tmp_path / "old", relocalise=False)
    new, world = await run(drifting, plan, tmp_path / "new")
    assert old.report["scans_empty"], "the drift is too small to matter: the test proves nothing"
    assert new.report["scans_empty"] == []
    # every scan lands where planned: each sees more of the part than its drifted twin did
    assert all(n.point_count > o.point_count for n, o in zip(new.scans, old.scans, strict=True))
    reloc = new.report["relocalisation"]
    assert reloc["anchor"]["source"] == "measurement AGV where its odometry says"
    assert reloc["stations_located"] == plan.scan_count and reloc["unresolved_count"] == 0
    # the AGV stood tens of mm off plan; the tracker placed it within its noise (tenths of a mm, mdeg)
    assert reloc["off_plan_mm_max"] > 50.0
    located_truth = new.report["ground_truth"]["relocalisation"]
    assert located_truth["err_to_truth_mm_max"] < 0.5 and located_truth["err_to_truth_deg_max"] < 0.02
    assert new.report["ground_truth"]["pose_err_mm_max"] < 0.5
    assert not world.motion.violations


async def test_unreachable_resolved_pose_is_reported_and_the_job_goes_on(generated, drifting, tmp_path):
    plan = first_scan_per_station(generated.sequence.plan, 1)
    arm = next(i for i, s in enumerate(plan.steps) if isinstance(s, MoveArm) and s.T_F_S is not None)
    far = np.array(plan.steps[arm].T_F_S)
    far[:3, 3] += [0.0, 0.0, 3000.0]  # 3 m above the planned pose: no joint solution from any station
    steps = list(plan.steps)
    steps.insert(arm + 2, plan.steps[arm].model_copy(update={"T_F_S": tuple(map(tuple, far.tolist()))}))
    steps.insert(arm + 3, Scan(label="out of reach"))
    result, _ = await run(drifting, Plan(name="unreachable", steps=steps), tmp_path)
    reloc = result.report["relocalisation"]
    assert result.report["scans"] == 2 and reloc["unresolved_count"] == 1
    (entry,) = reloc["unresolved"]
    assert entry["scan"] == 1 and entry["label"] == "out of reach" and "out of the arm's reach" in entry["reason"]
    assert result.scans[0].point_count > 1000  # the reachable pose before it was re-solved and scanned


async def test_an_opening_tracker_move_is_a_plain_relocation(generated, drifting, sim_config, tmp_path):
    plan = first_scan_per_station(generated.sequence.plan, 1)
    start = sim_config.sim.tracking_start
    moved = MoveTracker(x_mm=start.x_mm + 400.0, y_mm=start.y_mm + 200.0, heading_rad=np.radians(start.heading_deg))
    result, world = await run(drifting, Plan(name="relocated", steps=[moved, *plan.steps]), tmp_path)
    assert result.report["transfers"] == 0 and result.report["scans_empty"] == []
    # W is the camera frame at the new station, in the runner and in the truth it is scored against
    np.testing.assert_allclose(world.T_W_F @ world.T_F_C(), np.eye(4), atol=1e-9)
    assert result.report["ground_truth"]["pose_err_mm_max"] < 0.5
    assert result.report["relocalisation"]["anchor"]["step"] == 0


@pytest.mark.slow
async def test_a_scan_that_saw_nothing_is_left_out_of_the_correction(sim_config, tmp_path):
    from tandemscan.daemon.plans import default_plan_path

    band = Plan.load(default_plan_path())
    two = [i for i, s in enumerate(band.steps) if isinstance(s, Scan)][1]
    home = tuple(np.radians(sim_config.sim.arm_home_deg))
    plan = Plan(name="one empty", steps=[*band.steps[: two + 1], MoveArm(joints_rad=home), Scan(label="sky")])
    config = sim_config.model_copy(update={
        "correction": sim_config.correction.model_copy(update={"method": "icp"}),
        "inspection": sim_config.inspection.model_copy(update={"in_job": False}),
    })
    result, _ = await run(config, plan, tmp_path)
    assert result.report["scans_empty"] == [2]
    assert result.report["correction"]["enabled"] and result.report["correction"]["scans"] == 2


class MemoryJournal:
    """A step journal in memory (the runner's ``StepJournal``): commits and notes kept as JSON, as the store."""

    def __init__(self, committed: dict[int, dict] | None = None, notes: dict[int, dict] | None = None):
        self.committed = dict(committed or {})
        self.results: dict[int, dict] = {}
        self._notes = {k: dict(v) for k, v in (notes or {}).items()}
        self.resumes: list[dict] = []

    async def run_step(self, idx: int, fn):
        return await fn()

    async def note(self, idx: int, kind: str, value: dict) -> None:
        self._notes.setdefault(idx, {})[kind] = json.loads(json.dumps(value))

    def notes(self, idx: int) -> dict[str, dict]:
        return self._notes.get(idx, {})

    async def record_resume(self, idx: int, entry: dict) -> None:
        self.resumes.append(json.loads(json.dumps(entry)))

    async def commit(self, idx: int, kind: str, result: dict, scan_file=None, scan_points: int = 0) -> None:
        self.results[idx] = json.loads(json.dumps(result))


async def test_a_resumed_job_keeps_the_anchor_and_the_located_stations(generated, drifting, tmp_path):
    """Restart just before the last scan (where the sim's robots still stand): the anchor and every located
    station come back from the journal; a station lost on replay would be re-anchored or missing."""
    plan = first_scan_per_station(generated.sequence.plan, 3)
    async with CellSession(drifting) as session:
        first = MemoryJournal()
        full = await JobRunner(session, plan, drifting, tmp_path, journal=first).run()
        a = full.report["relocalisation"]
        cut = a["located"][-1]["step"] + 1
        assert isinstance(plan.steps[cut], Scan)
        again = MemoryJournal({i: first.results[i] for i in range(cut)}, first._notes)
        resumed = await JobRunner(session, plan, drifting, tmp_path, journal=again).run()  # reads its scan files
    b = resumed.report["relocalisation"]
    assert b["anchor"] == a["anchor"] and b["anchor"]["source"] == "measurement AGV where its odometry says"
    assert b["located"] == a["located"] and len(b["located"]) == plan.scan_count
    assert resumed.report["scans_empty"] == [] and resumed.report["scans"] == plan.scan_count


def assert_same(a, b, where: str = "state") -> None:
    """``a`` and ``b`` equal field by field, arrays exactly (values, shape and dtype)."""
    if dataclasses.is_dataclass(a):
        assert type(a) is type(b), where
        for f in dataclasses.fields(a):
            assert_same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and a.dtype == b.dtype and np.array_equal(a, b), where
    elif isinstance(a, (tuple, list)):
        assert type(a) is type(b) and len(a) == len(b), where
        for k, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{where}[{k}]")
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            assert_same(a[k], b[k], f"{where}[{k!r}]")
    else:
        assert type(a) is type(b) and a == b, f"{where}: {a!r} != {b!r}"


async def journaled_run(config, plan, root):
    """The daemon's path without its HTTP layer: the job in a job store, each step committed through the
    store's journal (:class:`StoreJournal`) under the job manager's checkpoints. Returns the runner and the
    journal as the store keeps it (committed results, notes)."""
    store = JobStore(root)
    job, _ = store.create_job(plan.name, {"plan": plan.model_dump(mode="json")}, len(plan.steps))
    store.set_state(job.id, "running")
    try:
        async with CellSession(config) as session:
            manager = JobManager(store, EventBus(), session.supervisor, runner=None)
            ctx = JobContext(store.begin_attempt(job.id), store, session.supervisor, manager, session.cell, config,
                             {}, session)
            runner = JobRunner(session, plan, config, store.job_dir(job.id), journal=StoreJournal(ctx))
            await runner.run()
        notes = {i: store.notes(job.id, i) for i in range(len(plan.steps))}
        return runner, store.committed_steps(job.id), notes
    finally:
        store.close()


async def test_a_journaled_job_replayed_through_apply_is_the_state_that_wrote_it(generated, drifting, tmp_path):
    """Two journaled jobs: AGV stations located and arm poses re-solved (drifting chassis), and the shipped plan
    with a coordinate transfer and the anchor noted before its first step. Their committed journals, replayed
    through ``apply`` from the state a job starts with, give the state each run ended with (the tracker-only
    stitch: the correction changes poses after the last step, not a step)."""
    from tandemscan.daemon.plans import default_plan_path

    band = Plan.load(default_plan_path())
    second_scan = [i for i, s in enumerate(band.steps) if isinstance(s, Scan)][1]
    transfer = next(i for i, s in enumerate(band.steps) if isinstance(s, MoveTracker))
    after = next(i for i, s in enumerate(band.steps) if isinstance(s, Scan) and i > transfer)
    cases = [
        ("located", first_scan_per_station(generated.sequence.plan, 2)),
        ("transfer", Plan(name="transfer", steps=[*band.steps[: second_scan + 1],
                                                  *band.steps[transfer - 2: after + 1]])),
    ]
    config = drifting.model_copy(update={"job": drifting.job.model_copy(update={"relocalise": True})})
    for name, plan in cases:
        runner, committed, notes = await journaled_run(config, plan, tmp_path / name)
        assert sorted(committed) == list(range(len(plan.steps)))
        records = journal_records(plan, committed, notes.__getitem__, runner.job_dir,
                                  opens_with_anchor(plan, relocalise=True))
        start = RunState(relocalisation=RelocalisationState(enabled=runner.resolving))
        replayed = replay_journal(start, records)
        assert_same(replayed, runner.state)
        state = runner.state
        assert len(state.scans) == plan.scan_count and state.relocalisation.T_F_W is not None
        if name == "located":
            assert runner.resolving and len(state.relocalisation.located) == plan.scan_count
        else:
            assert not runner.resolving and len(state.transfers) == state.tracker_station == 1


async def test_the_first_scan_after_a_resume_that_sees_nothing_where_the_plan_looks_at_the_part_pauses(sim_config,
                                                                                                        tmp_path):
    """Issue 42 row 9: resumed before the station's second scan, the part gone from the cell meanwhile: the scan that
    sees nothing where the plan's scanner pose looks at the part is not kept silently; the job pauses for the
    operator, and the operator's resume keeps what the scan sees (stated in ``scans_empty``)."""
    import copy

    from tandemscan.daemon.jobs.faults import ScanSawNothing
    from tandemscan.daemon.plans import default_plan_path
    from tandemscan.pipeline.geometry.raycast import make_scene

    band = Plan.load(default_plan_path())
    plan = band.model_copy(update={"steps": band.steps[:5]})  # move_measure, move_arm, scan, move_arm, scan
    config = sim_config.model_copy(update={
        "correction": sim_config.correction.model_copy(update={"enabled": False}),
        "inspection": sim_config.inspection.model_copy(update={"in_job": False}),
    })
    async with CellSession(config) as session:
        first = MemoryJournal()
        full = await JobRunner(session, plan, config, tmp_path, journal=first).run()
        assert full.report["scans_empty"] == []
        world = session.cell.simulation.world
        world.scene = make_scene(copy.deepcopy(world.mesh).translate((0.0, 0.0, 20000.0)))  # the part taken away
        again = MemoryJournal({i: first.results[i] for i in range(4)}, first._notes)
        with pytest.raises(ScanSawNothing, match="step 4 .* saw nothing where the plan's scanner pose looks at"):
            await JobRunner(session, plan, config, tmp_path, journal=again).run()
        assert 4 not in again.results
        kept = await JobRunner(session, plan, config, tmp_path, journal=again).run()  # the operator resumed
    assert kept.report["scans_empty"] == [1] and kept.report["scans"] == 2
