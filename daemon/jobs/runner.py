"""The job runner: executes a plan on the cell's devices, stitches every scan into the world, writes results.

Order (``docs/architecture.md``): measure (persist the raw scan, ``T_C_T``, joints and timestamps before anything
else) -> stitch (Eq. 1 into a voxel world map) -> export (``cloud.ply``, ``report.json``). A ``move_tracker``
step is a coordinate transfer (Eq. 2, :mod:`tandemscan.daemon.jobs.coordinate_transfer`) with the measurement robot
standing still. Steps run one at a time, so the two robots never move together. Each is measured into a record
(:mod:`tandemscan.daemon.jobs.records`), committed, and applied to the job's state
(:mod:`tandemscan.daemon.jobs.run_state`), the way a resumed job replays it. Heavy numeric work (scan writing,
stitching, correction, report and exports) runs where the world map lives (:mod:`tandemscan.daemon.jobs.stitcher`): a
worker process in the daemon, threads otherwise; the event loop only passes small records and file names.

A ``move_tracker`` before the job's first scan is a plain relocation: nothing is placed in W yet, so W becomes
the tracker camera frame where it then stands. With ``job.relocalise`` the runner places W in the plan's frame F
from one target reading at the start (the anchor, Eq. 5: the in-job inspection's registration to CAD) and,
where the plan has scanner poses ``T_F_S``, measures where the measurement AGV stands after each drive
(:mod:`tandemscan.daemon.jobs.agv_relocalisation`) and re-solves the arm for each ``move_arm`` step's planned pose, so a
drifting chassis still scans where the plan meant; a pose out of reach from there is scanned with the plan's
joints and listed in the report (``relocalisation.unresolved``).

Every motion goes through the session's gate (:mod:`tandemscan.daemon.cell.session`); what the job measures is told
to the session's observer (:mod:`tandemscan.daemon.cell.observer`), which on the simulated cell scores it against the
ground truth. Nothing here reads the truth.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from tandemscan.config.models import CellConfig
from tandemscan.daemon.calibration.current import installation_for_job, resolve_installation
from tandemscan.daemon.cell.motion import Robot
from tandemscan.daemon.cell.observer import JobObserver
from tandemscan.daemon.cell.session import CellSession, MotionGate
from tandemscan.daemon.cell.tracker_reading import read_at_rest, read_for_transfer
from tandemscan.daemon.jobs.agv_relocalisation import AgvRelocalisation
from tandemscan.daemon.jobs.coordinate_transfer import (
    RESUME_TOLERANCE_DEG,
    RESUME_TOLERANCE_MM,
    TransferReadings,
    poses_transfer_record,
    reestablish,
    transfer_record,
)
from tandemscan.daemon.jobs.faults import RobotsMovedWhileDown, ScanSawNothing, TooManyScansLeftOut
from tandemscan.daemon.jobs.records import (
    ArmMove,
    LiftMove,
    MeasureMove,
    ScanRecord,
    StepRecord,
    TrackerRelocation,
    TransferRecord,
    UntrackedScan,
)
from tandemscan.daemon.jobs.resume_check import (
    ArmOff,
    ChassisOff,
    agv_shift,
    arm_off_journal,
    as_tuple,
    chassis_off_journal,
    chassis_pose_of,
    journaled_joints,
    last_target_at_rest,
    planned_scanner_pose,
    relocalise_odometry,
    view_reaches_box,
)
from tandemscan.daemon.jobs.run_state import (
    RelocalisationState,
    RunState,
    apply,
    journal_records,
    opens_with_anchor,
    replay_journal,
)
from tandemscan.daemon.jobs.snapshot import JobSnapshot
from tandemscan.daemon.jobs.step_journal import NoJournal, StepJournal
from tandemscan.daemon.jobs.stitcher import LocalWorldMap, ProcessWorldMap
from tandemscan.daemon.store.rows import DAMAGED_NOTE
from tandemscan.drivers.errors import TargetNotVisible
from tandemscan.drivers.interfaces import ChassisPose, TrackerReading
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.kinematics import ArmKinematics
from tandemscan.pipeline.geometry.part import load_part_mesh
from tandemscan.pipeline.io.raw_scan import remove_thinned_copies
from tandemscan.pipeline.job_report import REPORT_FILE, JobHistory, JobReport
from tandemscan.pipeline.planning.plan import MoveArm, MoveLift, MoveMeasure, MoveTracker, Plan, Scan
from tandemscan.pipeline.stitching.relocalise import Relocaliser

log = logging.getLogger(__name__)

#: the journal note of a scan step whose left-out scan paused the job for the operator (the run after the
#: operator's resume leaves it out)
PAUSED_FOR_GAPS = "paused_for_gaps"
#: the journal note of a resumed step whose robots were off the journal and paused the job for the operator (the
#: run after the operator's resume goes on from where they stand)
ROBOTS_CHECKED = "robots_checked"
#: the journal note of the first scan after a resume that saw nothing where the plan looks at the part and paused
#: the job for the operator (the run after the operator's resume keeps what it sees)
EMPTY_SCAN_CHECKED = "empty_scan_checked"

_DESCRIBE = {"move_tracker": "coordinate transfer: moving the tracking robot", "move_measure": "moving the measurement "
             "robot", "move_lift": "moving the lifting column", "move_arm": "moving the arm", "scan": "scanning"}


class JobError(Exception):
    """A job could not be run (bad plan for this cell, a device fault, missing calibration)."""


@dataclass(frozen=True)
class JobProgress:
    """Progress of a running job: steps done of total and what is happening now."""

    done: int
    total: int
    message: str


@dataclass
class JobResult:
    """What a finished job left behind: its folder, ``cloud.ply`` and ``report.json`` (``job_report``, with the
    simulator's scores where it has them, which are written beside it as ``ground_truth.json``; ``report`` is its
    JSON) and its scan records at their final poses."""

    job_dir: Path
    cloud_file: Path
    report_file: Path
    job_report: JobReport
    scans: list[ScanRecord] = field(default_factory=list)

    @functools.cached_property
    def report(self) -> dict:
        """The content of ``report.json`` with the observer's ``ground_truth`` (``ground_truth.json``'s)."""
        return self.job_report.to_json()


class JobRunner:
    """Runs one plan on the cell of an open ``session`` into ``job_dir``: every motion through the session's
    gate, steps through ``journal`` (none: a run that cannot resume), what it measures told to the session's
    observer (the simulated cell's ground truth; none on a real cell). ``state`` is the job's state so far
    (:class:`~tandemscan.daemon.jobs.run_state.RunState`): each step is measured into a record, committed, then applied.
    A scan whose target the tracker cannot see is read again (``tracker.scan_read_retries``) and then left out; one
    more than ``max_scans_left_out`` (None: no limit) raises :class:`~tandemscan.daemon.jobs.faults.TooManyScansLeftOut`
    once, so that the job pauses for the operator: run again, that step is left out if the target is still hidden.
    ``history`` (a journaled job) returns the journal's resumes and attempts for its report, asked once every step
    is committed."""

    def __init__(
        self,
        session: CellSession,
        plan: Plan,
        config: CellConfig,
        job_dir: Path,
        progress: Callable[[JobProgress], None] | None = None,
        journal: StepJournal | None = None,
        worldmap: LocalWorldMap | ProcessWorldMap | None = None,
        max_scans_left_out: int | None = None,
        history: Callable[[], Awaitable[JobHistory]] | None = None,
    ):
        """Nine parameters: what every run has (the open session, the plan, the configuration, the job folder),
        then each collaborator a run may add, with its default: a progress sink, the daemon's journal, a world
        map in a worker process, the scans-left-out limit and the journal's history for the report."""
        self.cell = session.cell
        self.gate: MotionGate = session.gate
        self.plan = plan
        self.config = config = resolve_installation(config)  # "current": the cell's current calibration or nominal
        self.job_dir = Path(job_dir)
        self.progress = progress or (lambda p: None)
        self.journal = journal or NoJournal()
        self.observer: JobObserver | None = session.job_observer(self.job_dir.name, bool(self.journal.committed))
        self.installation = installation_for_job(config)
        self.worldmap = worldmap if worldmap is not None else LocalWorldMap(
            config.job.voxel_mm, config.compute.reads_scan_store)
        self.correction: dict = {"enabled": False}
        self.max_scans_left_out = max_scans_left_out
        self.history = history  # the journal's resumes of every attempt, for the report (none: not journaled)
        self._reserved_indices: set[int] = set()  # scan indices of damaged scans, measured again at the end
        self._first_scan_resumed: int | None = None  # the step of the first scan after a resume (checked if empty)
        # with relocalisation on, W is placed in the plan's frame F at the start (the anchor: the inspection's
        # registration to CAD); the AGV is located after each drive where the plan has scanner poses to re-solve
        self.relocalisation: AgvRelocalisation | None = None
        if config.job.relocalise:
            self.relocalisation = AgvRelocalisation(
                Relocaliser(config.arm, config.scanner, self.installation), self.cell, self.gate,
                config.arm.timeout_s, self.journal, plan, self.read_target, self.observer)
        self.resolving = self.relocalisation is not None and any(
            isinstance(s, MoveArm) and s.T_F_S is not None for s in plan.steps)
        self.state = RunState(relocalisation=RelocalisationState(enabled=self.resolving))

    async def read_target(self) -> TrackerReading:
        """The target pose at rest, averaged over ``tracker.samples_per_reading`` readings."""
        return await read_at_rest(self.cell.tracker, self.config.tracker.samples_per_reading, self.config.tracker)

    async def run(self) -> JobResult:
        """Execute every step, then stitch and export. Raises :class:`JobError` on failure. The scans' thinned
        copies kept beside them for the end of the job (``raw_scan.keep_thinned_copy``) are removed when it ends,
        done, failed or cancelled, in a thread (a file a scan, on the scan store's shared filesystem)."""
        try:
            return await self._run()
        finally:
            await asyncio.to_thread(remove_thinned_copies, self.job_dir)

    async def _run(self) -> JobResult:
        started = time.monotonic()
        (self.job_dir / "scans").mkdir(parents=True, exist_ok=True)
        total = len(self.plan.steps) + 1
        async with self.gate.motion(Robot.MEASURE) as robot:
            await robot.arm.enable()
        if self.cell.lift is not None:
            self.state = replace(self.state, lift_mm=await self.cell.lift.height())
        committed = self.journal.committed
        await self._replay()
        if opens_with_anchor(self.plan, self.relocalisation is not None) and 0 not in committed:
            self.state = apply(self.state, await self.relocalisation.anchor(0, self.state))
        resuming = bool(committed)
        # scans whose files were damaged, taken out of the journal on resume: measured again once the plan is done
        again = [i for i, step in enumerate(self.plan.steps)
                 if isinstance(step, Scan) and i not in committed and DAMAGED_NOTE in self.journal.notes(i)]
        self._reserved_indices = {self.journal.notes(i)[DAMAGED_NOTE]["scan_index"] for i in again} - {None}
        order = [*(i for i in range(len(self.plan.steps)) if i not in again), *again]
        for at, i in enumerate(order):
            if i in committed:
                continue
            step = self.plan.steps[i]
            if resuming:
                await self._reestablish(i, step, i in again)
                self._first_scan_resumed = next((k for k in order[at:] if k not in committed and k not in again
                                                 and isinstance(self.plan.steps[k], Scan)), None)
                resuming = False
            self.progress(JobProgress(i, total, _DESCRIBE[step.kind]))
            if i in again:
                record = await self.journal.run_step(i, lambda i=i: self._measure_again(i))
            else:
                record = await self.journal.run_step(i, lambda i=i, step=step: self._execute(i, step))
            scan = (record.file, record.point_count) if isinstance(record, ScanRecord) else ()
            await self.journal.commit(i, step.kind, record.to_json(), *scan)
            self.state = apply(self.state, record)
        if resuming:  # every step was committed before this attempt: it resumes in the export, nothing moves
            await self.journal.record_resume(len(self.plan.steps), {"step": len(self.plan.steps), "kind": "export"})
        measured_at = time.monotonic()  # the last step committed: from here the operator waits for the report
        self.progress(JobProgress(total - 1, total, "correcting the stitch, writing cloud and report"))
        job = self.snapshot()
        if self.history is not None:  # every resume is journaled by now, the export's included
            job.history = await self.history()
        finished = await self.worldmap.finish(job, started, measured_at)
        self.correction = finished.correction.section
        final = {s.index: T for s, T in zip(self.state.scans, finished.correction.poses, strict=True)}
        # JobResult's records carry the final poses; report.json keeps both (finish.FinishedJob)
        self.state = replace(self.state, scans=tuple(replace(s, T_W_S=final[s.index]) for s in self.state.scans))
        self.progress(JobProgress(total, total, "done"))
        return JobResult(self.job_dir, self.job_dir / "cloud.ply", self.job_dir / REPORT_FILE, finished.report,
                         list(self.state.scans))

    async def _replay(self) -> None:
        """Rebuild the state from the steps committed before a restart (no device is touched) and the world map
        from their scan files."""
        records = journal_records(self.plan, self.journal.committed, self.journal.notes, self.job_dir,
                                  opens_with_anchor(self.plan, self.relocalisation is not None))
        self.state = replay_journal(self.state, records)
        for record in self.state.scans:
            await self.worldmap.add_scan(record.file, record.T_W_S)

    async def _execute(self, i: int, step) -> StepRecord:
        """One step on the devices, measured into its record (the state is not changed here)."""
        if isinstance(step, MoveTracker):
            if not self.state.scans:
                return await self._relocate_tracker(step, i)
            return await self._transfer(step, i)
        if isinstance(step, MoveMeasure):
            async with self.gate.motion(Robot.MEASURE) as robot:
                odo = await robot.chassis.move_to(ChassisPose(step.x_mm, step.y_mm, step.heading_rad),
                                                  self.config.measure_chassis.timeout_s)
            entry = None
            if self.resolving:
                planned = F.planar_pose(step.x_mm, step.y_mm, step.heading_rad)
                entry = await self.relocalisation.after_drive(i, self.state, planned)
            return MeasureMove((odo.x_mm, odo.y_mm, odo.heading_rad), entry)
        if isinstance(step, MoveLift):
            return await self._move_lift(step)
        if isinstance(step, MoveArm):
            joints, entry = np.array(step.joints_rad), None
            if self.resolving and step.T_F_S is not None:
                joints, entry = await self.relocalisation.arm_target(i, step, self.state)
            async with self.gate.motion(Robot.MEASURE) as robot:
                await robot.arm.move_joints(joints, self.config.arm.timeout_s)
            return ArmMove(joints, entry)
        try:
            return await self._scan(empty_check=i if i == self._first_scan_resumed else None)
        except TargetNotVisible as e:  # e.g. a nearby view the plan's tracker cover did not check: go on
            return await self._leave_out(i, step.label if isinstance(step, Scan) else "", e.reason)

    async def _leave_out(self, i: int, label: str, reason: str) -> UntrackedScan:
        """Scan step ``i`` left out (the tracker cannot see the target); beyond ``max_scans_left_out`` the first time
        a :class:`TooManyScansLeftOut` (noted in the journal, so that the run after the operator's resume goes on)."""
        left_out = len(self.state.relocalisation.untracked)
        if (self.max_scans_left_out is not None and left_out >= self.max_scans_left_out
                and PAUSED_FOR_GAPS not in self.journal.notes(i)):
            await self.journal.note(i, PAUSED_FOR_GAPS, {"reason": reason})
            raise TooManyScansLeftOut(f"step {i} ({label}): the tracker cannot see the target ({reason}); "
                                      f"{left_out} scans left out already, the limit is {self.max_scans_left_out} "
                                      "([job] max_scans_left_out); clear the tracker's sight line and resume (that "
                                      "scan is then left out if the target is still hidden), or cancel")
        log.warning("step %d (%s): scan left out, %s", i, label, reason)
        return UntrackedScan(i, label, reason)

    async def _measure_again(self, i: int) -> StepRecord:
        """Scan step ``i`` again, its file found damaged on resume: the measurement robot back at the step's AGV
        station, column height and arm joints (the arm's as committed), then the scan under its old index, stitched
        from where the tracker stands now; left out (and so stated) if the tracker cannot see the target there."""
        steps, committed = self.plan.steps[:i], self.journal.committed
        drive = next((s for s in reversed(steps) if isinstance(s, MoveMeasure)), None)
        lift = next((s for s in reversed(steps) if isinstance(s, MoveLift)), None)
        arm = next((k for k in reversed(range(i)) if isinstance(steps[k], MoveArm)), None)
        if lift is not None:
            await self._move_lift(lift)
        async with self.gate.motion(Robot.MEASURE) as robot:
            if drive is not None:
                await robot.chassis.move_to(ChassisPose(drive.x_mm, drive.y_mm, drive.heading_rad),
                                            self.config.measure_chassis.timeout_s)
            if arm is not None:
                joints = ArmMove.from_json(committed[arm]).joints_rad if arm in committed else steps[arm].joints_rad
                await robot.arm.move_joints(np.asarray(joints), self.config.arm.timeout_s)
        damaged = self.journal.notes(i)[DAMAGED_NOTE]
        log.warning("step %d: measuring again the scan whose file %s was damaged (%s)", i, damaged["file"],
                    damaged["reason"])
        try:
            return await self._scan(damaged["scan_index"])
        except TargetNotVisible as e:
            return await self._leave_out(i, self.plan.steps[i].label, e.reason)

    async def _move_lift(self, step: MoveLift) -> LiftMove:
        """Raise or lower the measurement AGV's lifting column, inside the measurement robot's motion gate."""
        if self.cell.lift is None:
            raise JobError("the plan moves a lifting column but this cell has none ([lift] enabled = false)")
        async with self.gate.motion(Robot.MEASURE) as robot:
            return LiftMove(await robot.lift.move_to(step.height_mm, self.config.lift.timeout_s))

    async def _reestablish(self, i: int, step, measuring_again: bool) -> None:
        """After a restart or a pause, before moving anything: the arm's joints read back against the journal, a
        fresh target reading and each AGV's odometry against the journal (:mod:`~tandemscan.daemon.jobs.resume_check`).
        An AGV off its journaled pose: :meth:`_relocalise_after_restart`. An arm off its journaled joints (a move cut
        short, a jogged arm; not checked before a scan ``measuring_again``, whose own moves put the robot back) is
        then moved back to them, re-running the last arm move from where it stands, and the target read again
        there. Where both AGVs are where the journal left them (or only their odometry restarted) and the target
        has not moved since the last journaled reading, that reading and the fresh one must agree; if not, the
        tracker was moved while the daemon was down and its frame is re-established from the fresh one
        (:func:`~tandemscan.daemon.jobs.coordinate_transfer.reestablish`). The resume is journaled with what was
        found."""
        entry: dict = {"step": i, "kind": step.kind}
        joints = await self.cell.arm.joints()
        arm = None if measuring_again else arm_off_journal(
            journaled_joints(self.plan, self.journal.committed, i), joints, self.config.job.resume_joint_tolerance_deg)
        fresh = await self._fresh_reading(i, entry)
        mid_transfer = isinstance(step, MoveTracker)
        tracker_may_have_moved = mid_transfer and "before" in self.journal.notes(i)
        job = self.config.job
        off = await chassis_off_journal(self.cell, self.plan, self.journal.committed, i, tracker_may_have_moved,
                                        job.resume_pose_tolerance_mm, job.resume_pose_tolerance_deg)
        if arm is not None:
            entry["arm_off_journal"] = arm.entry()
            log.warning("resume at step %d: the arm stands %.2f deg off the joints the journal left it at", i,
                        arm.off_deg)
        if off:
            entry["chassis_off_journal"] = {name: o.entry() for name, o in off.items()}
            entry |= await self._relocalise_after_restart(i, fresh, off, joints, arm, tracker_may_have_moved)
        if arm is not None and not entry.get("arm_returned"):
            fresh = await self._return_arm(i, arm, entry)
        if fresh is not None and (not off or "odometry_relocalised" in entry):
            self.state, checked = reestablish(self.state, i, fresh.T_C_T, mid_transfer)
            entry |= checked
        await self.journal.record_resume(i, entry)

    async def _fresh_reading(self, i: int, entry: dict) -> TrackerReading | None:
        """The target at rest at a resume; None, noted in the resume's ``entry``, where the tracker cannot see it."""
        try:
            return await self.read_target()
        except TargetNotVisible as e:
            entry["fresh_reading"] = f"target not visible: {e.reason}"
            log.warning("resume at step %d: %s", i, entry["fresh_reading"])
            return None

    async def _return_arm(self, i: int, arm: ArmOff, entry: dict) -> TrackerReading | None:
        """The arm moved back to the joints the journal left it at (the last arm move run again from where it stands,
        through the gate), ``entry`` told so; the target read again there."""
        async with self.gate.motion(Robot.MEASURE) as robot:
            await robot.arm.move_joints(arm.journaled, self.config.arm.timeout_s)
        entry["arm_returned"] = True
        log.warning("resume at step %d: the arm moved back to the journaled joints", i)
        return await self._fresh_reading(i, entry)

    async def _relocalise_after_restart(self, i: int, fresh: TrackerReading | None, off: dict[str, ChassisOff],
                                        joints: np.ndarray, arm: ArmOff | None, tracker_may_have_moved: bool) -> dict:
        """AGVs off their journaled poses at a resume before step ``i``, the arm at ``joints`` (rad; ``arm``: off its
        journaled ones): where the tracker sees the target where the journal left it
        (:meth:`_target_where_journaled`), their odometry restarted and is set back; where it does not (and the
        tracker stood still: not ``tracker_may_have_moved`` in a transfer) and only one AGV's odometry moved, that
        one is re-localised (the tracker's frame re-established from the still target,
        read again once the arm is back where it was read, or the measurement AGV located by the tracker);
        otherwise, once, the operator decides (:class:`~tandemscan.daemon.jobs.faults.RobotsMovedWhileDown`) and a
        resume goes on from where they stand. Returns the resume's journal fields."""
        fields: dict = {}
        unmoved = await self._target_where_journaled(i, fresh, joints, arm is not None)
        if tracker_may_have_moved and not unmoved:
            unmoved = None  # the target seen elsewhere by a tracker that may have driven on: no witness
        if unmoved:
            await relocalise_odometry(self.gate, off)
            log.warning("resume at step %d: %s odometry restarted; set back to the journal's poses", i, sorted(off))
            return {"odometry_relocalised": sorted(off)}
        if unmoved is False and list(off) == ["tracking_chassis"] and fresh is not None:
            if arm is not None:
                fresh = await self._return_arm(i, arm, fields)
            if fresh is not None:
                self.state, checked = reestablish(self.state, i, fresh.T_C_T, False)
                if checked.get("reestablished"):
                    return fields | checked | {"relocalised": "tracking_chassis"}
        if unmoved is False and list(off) == ["measure_chassis"] and self.relocalisation is not None:
            drive = next(s for s in reversed(self.plan.steps[:i]) if isinstance(s, MoveMeasure))
            planned = F.planar_pose(drive.x_mm, drive.y_mm, drive.heading_rad)
            entry = await self.relocalisation.after_drive(i, self.state, planned)
            if entry.located is not None:  # where the tracker found it in F, its odometry's frame (the plan's)
                located = chassis_pose_of(entry.T_F_V2)
                async with self.gate.motion(Robot.MEASURE) as robot:
                    await robot.chassis.set_odometry(located)
                self.state = apply(self.state, MeasureMove(as_tuple(located), entry))
                log.warning("resume at step %d: the measurement AGV was moved while the daemon was down; "
                            "re-localised %s", i, entry.located)
                return fields | {"relocalised": "measure_chassis", "located": entry.located}
        if ROBOTS_CHECKED not in self.journal.notes(i):
            await self.journal.note(i, ROBOTS_CHECKED, {name: o.entry() for name, o in off.items()})
            where = "; ".join(f"{name} at ({o.reported.x_mm:.0f}, {o.reported.y_mm:.0f}) mm, the journal left it "
                              f"at ({o.journaled.x_mm:.0f}, {o.journaled.y_mm:.0f}) mm" for name, o in off.items())
            raise RobotsMovedWhileDown(f"resume at step {i}: {where}, and the tracker cannot tell which robot moved; "
                                       "put them back where the journal left them and resume, or cancel")
        log.warning("resume at step %d: the operator resumed with %s off the journal", i, sorted(off))
        return fields | {"resumed_by_operator": True}

    async def _target_where_journaled(self, i: int, fresh: TrackerReading | None, joints: np.ndarray,
                                      arm_off: bool) -> bool | None:
        """Whether the tracker sees the target where the journal left it: the fresh reading against the last still
        one (within the resume tolerance of Eq. 2's check) where the arm stands where that was read; else the
        measurement AGV by the fresh reading at the arm's ``joints`` (rad) against where the last scan's reading put
        it (Eq. 5, ``[job] resume_pose_tolerance_*``: the arm may have moved since); else the measurement AGV
        located again against where it was last located; None where none of these can be asked."""
        job = self.config.job
        last = self.state.last_still_T_C_T
        if fresh is not None and last is not None and not arm_off:
            d_mm, d_rad = F.pose_error(fresh.T_C_T, last)
            return bool(d_mm <= RESUME_TOLERANCE_MM and np.degrees(d_rad) <= RESUME_TOLERANCE_DEG)
        then = last_target_at_rest(self.plan, self.journal.committed, i)
        if fresh is not None and then is not None:
            d_mm, d_deg = agv_shift(self.installation, ArmKinematics(self.config.arm), self.state.lift_mm, then,
                                    self.state.T_W_C, fresh.T_C_T, joints)
            log.info("resume at step %d: the measurement AGV %.2f mm / %.3f deg from where the last scan's reading "
                     "put it", i, d_mm, d_deg)
            return bool(d_mm <= job.resume_pose_tolerance_mm and d_deg <= job.resume_pose_tolerance_deg)
        journaled = self.state.relocalisation.T_F_V2
        if self.relocalisation is None or journaled is None:
            return None
        located, reloc = await self.relocalisation.locate(i, self.state)
        if located is None:
            return None
        d_mm, d_rad = F.pose_error(reloc.T_F_V2, journaled)
        return bool(d_mm <= job.resume_pose_tolerance_mm and np.degrees(d_rad) <= job.resume_pose_tolerance_deg)

    async def _relocate_tracker(self, step: MoveTracker, i: int) -> TrackerRelocation:
        """A tracker move before the first scan: no transfer, W becomes the camera frame where it now stands."""
        async with self.gate.motion(Robot.TRACKING) as robot:
            odo = await robot.chassis.move_to(
                ChassisPose(step.x_mm, step.y_mm, step.heading_rad), self.config.tracking_chassis.timeout_s
            )
        record = TrackerRelocation((odo.x_mm, odo.y_mm, odo.heading_rad))
        if self.observer is not None:
            self.observer.world_defined()
        log.info("tracker relocated before the first scan: the world frame is its camera frame there")
        if self.relocalisation is not None:
            moved = apply(self.state, record)
            anchored = apply(moved, await self.relocalisation.anchor(i, moved))
            record = replace(record, relocalisation=anchored.relocalisation.entry())
        return record

    async def _transfer(self, step: MoveTracker, i: int = -1) -> StepRecord:
        """Eq. 2: read the still target, move the tracker, read it again, re-place the tracker in W; with
        ``tracker.transfer_arm_poses`` > 1, or where the target is hidden at the transfer's own pose, at the arm
        poses :meth:`_transfer_poses` finds.

        The reading before the move (and the tracking chassis' odometry) is journaled before the tracker moves,
        so a transfer interrupted by a crash, a safety stop or a device fault completes from it (the target stays
        still meanwhile), and one of a job that fails or is cancelled is undone (:func:`return_from_transfer`).
        The transfer's entry carries its error prior for the pose graph: the still target's origin in W and the
        covariance of both readings (``uncertainty.transfer_covariance``)."""
        noted = self.journal.notes(i).get("before")
        if self.config.tracker.transfer_arm_poses > 1 or (noted is not None and "poses" in noted):
            return await self._transfer_poses(step, i)
        if noted is not None:
            before_T_C_T, before_cov = np.array(noted["T_C_T"]), np.array(noted["covariance"])
        else:
            try:
                before = await read_for_transfer(self.cell.tracker, self.config.tracker)
            except TargetNotVisible:  # hidden at the transfer's own pose: read it at another pose of the station
                return await self._transfer_poses(step, i)
            before_T_C_T, before_cov = before.T_C_T, before.covariance
            odo = await self.cell.tracking_chassis.odometry()  # where an abandoned transfer returns the tracker
            await self.journal.note(i, "before", {"T_C_T": before_T_C_T.tolist(), "covariance": before_cov.tolist(),
                                                  "odometry": [odo.x_mm, odo.y_mm, odo.heading_rad]})
        odo = await self._move_tracker(step)
        after = await read_for_transfer(self.cell.tracker, self.config.tracker)
        return self._transferred(transfer_record(self.state, before_T_C_T, before_cov, after, odo))

    async def _move_tracker(self, step: MoveTracker) -> tuple[float, float, float]:
        async with self.gate.motion(Robot.TRACKING) as robot:
            odo = await robot.chassis.move_to(
                ChassisPose(step.x_mm, step.y_mm, step.heading_rad), self.config.tracking_chassis.timeout_s
            )
        return (odo.x_mm, odo.y_mm, odo.heading_rad)

    def _transferred(self, record: TransferRecord) -> TransferRecord:
        if self.observer is not None:
            self.observer.tracker_transferred(record.station, record.T_W_C)
        log.info("coordinate transfer", extra={"station": record.station})
        return record

    async def _transfer_poses(self, step: MoveTracker, i: int) -> TransferRecord:
        """The transfer over ``tracker.transfer_arm_poses`` arm poses (docs/architecture.md, "Coordinate
        transfers"): the readings before the move, journaled (:class:`TransferReadings`); the tracker moves;
        the same joints read back in reverse order, so the arm ends where it stood; every arm move gated."""
        readings = TransferReadings(self.cell, self.gate, self.config, self.installation, self.plan, self.journal)
        before, dropped = await readings.before_move(step, i)
        odo = await self._move_tracker(step)
        after, hidden = await readings.after_move(before)
        return self._transferred(poses_transfer_record(self.state, before, after, odo, self.config, self.installation,
                                                       dropped + hidden))

    async def _read_for_scan(self) -> TrackerReading:
        """The target at rest for a scan; a target the tracker cannot see is read again ``scan_read_retries``
        times, ``scan_read_retry_s`` apart (nothing moves meanwhile), before :class:`TargetNotVisible` is raised."""
        cfg = self.config.tracker
        for retry in range(cfg.scan_read_retries):
            try:
                return await self.read_target()
            except TargetNotVisible as e:
                log.info("scan: %s; reading again in %.1f s (%d of %d)", e.reason, cfg.scan_read_retry_s, retry + 1,
                         cfg.scan_read_retries)
            await asyncio.sleep(cfg.scan_read_retry_s)
        return await self.read_target()

    async def _scan(self, index: int | None = None, empty_check: int | None = None) -> ScanRecord:
        """Capture and read at rest, persist raw data first, then stitch into the world map; ``index`` among the
        job's scans (default: the next). A capture of no point at step ``empty_check`` (the first scan after a
        resume) is checked first (:meth:`_check_empty_scan`)."""
        frame = await self.cell.scanner.capture(self.config.scanner.timeout_s)
        if empty_check is not None and len(frame.points_mm) == 0:
            await self._check_empty_scan(empty_check)
        reading = await self._read_for_scan()
        joints = await self.cell.arm.joints()
        if index is None:  # the next, past those kept for the scans measured again
            index = max({s.index for s in self.state.scans} | self._reserved_indices, default=-1) + 1
        T_W_C = self.state.T_W_C
        file = self.job_dir / "scans" / f"scan-{index:04d}.npz"
        arrays = {  # written (points as float32) and stitched where the map lives, not on the event loop
            "points_S_mm": frame.points_mm,
            "T_C_T": reading.T_C_T,
            "tracker_covariance": reading.covariance,
            "joints_rad": joints,
            "scan_timestamp_s": np.array(frame.timestamp_s),
            "tracker_timestamp_s": np.array(reading.timestamp_s),
            "T_W_C": T_W_C,
        }
        if frame.normals is not None:
            arrays["normals_S"] = frame.normals
        T_W_S = F.compose(T_W_C, reading.T_C_T, self.installation.T_T_S)
        await self.worldmap.add_scan(  # the file is durable before this returns; its pairs registered meanwhile
            file, T_W_S, arrays, pairs={"correction": self.config.correction, "station": self.state.tracker_station,
                                        "transfers": [t.entry() for t in self.state.transfers],
                                        "T_T_S": self.installation.T_T_S})
        if self.observer is not None:
            self.observer.scan_measured(index)
        return ScanRecord(index, self.state.tracker_station, file, reading, joints, T_W_C.copy(), T_W_S,
                          len(frame.points_mm))

    async def _check_empty_scan(self, i: int) -> None:
        """The first scan after a resume (step ``i``) saw nothing. Where the plan's scanner pose looks at the part (its
        optical axis within the working range reaches into the part's bounding box,
        :func:`~tandemscan.daemon.jobs.resume_check.view_reaches_box`), the robots may not stand where the resume found
        them, or the part is not in place: the job pauses for the operator, once
        (:class:`~tandemscan.daemon.jobs.faults.ScanSawNothing`); run again, the scan is taken and kept as it is."""
        if EMPTY_SCAN_CHECKED in self.journal.notes(i):
            log.warning("step %d: the first scan after the resume saw nothing again; kept (the operator resumed)", i)
            return
        T_F_S = planned_scanner_pose(self.plan, self.journal.committed, i, self.installation,
                                     ArmKinematics(self.config.arm), self.state.lift_mm)
        if T_F_S is None:
            return
        vertices = np.asarray((await asyncio.to_thread(load_part_mesh, self.config.part)).vertices)
        scanner = self.config.scanner
        if not view_reaches_box(T_F_S, vertices.min(axis=0), vertices.max(axis=0), scanner.range_min_mm,
                                scanner.range_max_mm):
            return
        joints = await self.cell.arm.joints()
        await self.journal.note(i, EMPTY_SCAN_CHECKED, {"joints_rad": joints.tolist()})
        label = self.plan.steps[i].label if isinstance(self.plan.steps[i], Scan) else ""
        raise ScanSawNothing(f"step {i} ({label}): the first scan after the resume saw nothing where the plan's "
                             f"scanner pose looks at the part (arm at {np.degrees(joints).round(1).tolist()} deg); "
                             "check that the part is in place and the robots where the plan puts them, then resume "
                             "(the scan is taken again and kept as it is), or cancel")

    def snapshot(self, scans: list[ScanRecord] | None = None) -> JobSnapshot:
        """The job's state for its end-of-job work (correction, report, exports) where the map lives; ``scans``
        (default: all) are the ones that work sees."""
        scorer = self.observer.scorer() if self.observer is not None else None
        state = self.state
        return JobSnapshot(self.job_dir, self.plan, self.config, self.installation,
                           list(scans or state.scans),
                           [t.entry() for t in state.transfers], dict(self.correction), scorer,
                           T_F_W=state.relocalisation.T_F_W, relocalisation=state.relocalisation.report())
