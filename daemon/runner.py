"""The job runner: executes a plan on the cell's devices, stitches every scan into the world, writes results.

Order per DESIGN.md section 5: measure (persist the raw scan, ``T_C_T``, joints and timestamps before anything
else) -> stitch (Eq. 1 into a voxel world map) -> export (``cloud.ply``, ``report.json``). A ``move_tracker``
step is a coordinate transfer (Eq. 2) with the measurement robot standing still. Steps run one at a time, so
the two robots never move together. Heavy numeric work (scan writing, stitching, correction, report and
exports) runs where the world map lives (:mod:`tandemscan.daemon.stitcher`): a worker process in the daemon,
threads otherwise; the event loop only passes small records and file names.

A ``move_tracker`` before the job's first scan is a plain relocation: nothing is placed in W yet, so W becomes
the tracker camera frame where it then stands. With ``job.relocalise`` the runner places W in the plan's frame F
from one target reading at the start (the anchor, Eq. 5: the in-job inspection's registration to CAD) and,
where the plan has scanner poses ``T_F_S``, measures where the measurement AGV stands after each drive
(:mod:`tandemscan.pipeline.stitching.relocalise`) and re-solves the arm for each ``move_arm`` step's planned pose, so a
drifting chassis still scans where the plan meant; a pose out of reach from there is scanned with the plan's
joints and listed in the report (``relocalisation.unresolved``).

Every motion goes through the session's gate (:mod:`tandemscan.daemon.session`); what the job measures is told
to the session's observer (:mod:`tandemscan.daemon.observer`), which on the simulated cell scores it against the
ground truth. Nothing here reads the truth.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol, TypeVar

import numpy as np
from tandemscan.config.models import CellConfig
from tandemscan.daemon.observer import JobObserver
from tandemscan.daemon.session import CellSession, MotionGate
from tandemscan.daemon.snapshot import JobSnapshot
from tandemscan.daemon.stitcher import LocalWorldMap, ProcessWorldMap, export
from tandemscan.daemon.supervisor import MEASURE_ROBOT, TRACKING_ROBOT
from tandemscan.daemon.tracker_reading import read_at_rest
from tandemscan.drivers.errors import TargetNotVisible
from tandemscan.drivers.interfaces import ChassisPose, TrackerReading
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.uncertainty import transfer_covariance
from tandemscan.pipeline.planning.plan import MoveArm, MoveLift, MoveMeasure, MoveTracker, Plan, Scan
from tandemscan.pipeline.stitching.installation import Installation
from tandemscan.pipeline.stitching.relocalise import Relocaliser

log = logging.getLogger(__name__)

# A fresh reading at resume that differs more than this from the journaled one (target still) means the
# tracker was moved while the daemon was down: its frame is then re-established from the fresh reading.
RESUME_TOLERANCE_MM = 0.5
RESUME_TOLERANCE_DEG = 0.05
T = TypeVar("T")


class JobError(Exception):
    """A job could not be run (bad plan for this cell, a device fault, missing calibration)."""


@dataclass(frozen=True)
class JobProgress:
    """Progress of a running job: steps done of total and what is happening now."""

    done: int
    total: int
    message: str


@dataclass
class ScanRecord:
    """One measured pose: the raw data and its world placement (mm)."""

    index: int
    tracker_station: int
    file: Path
    reading: TrackerReading
    joints_rad: np.ndarray
    T_W_C: np.ndarray
    T_W_S: np.ndarray
    point_count: int


@dataclass
class JobResult:
    """What a finished job left behind."""

    job_dir: Path
    cloud_file: Path
    report_file: Path
    report: dict
    scans: list[ScanRecord] = field(default_factory=list)


class StepJournal(Protocol):
    """Where a resumable run commits its steps (the daemon's store). ``committed`` maps a step index to
    the result committed for it; a run skips those steps and rebuilds its state from their results. Motion
    is not the journal's: it goes through the session's gate (:class:`~tandemscan.daemon.session.MotionGate`)."""

    committed: dict[int, dict]

    async def run_step(self, idx: int, fn: Callable[[], Awaitable[T]]) -> T:
        """Run one step (pause, cancel and safety stops are handled here)."""
        ...

    async def note(self, idx: int, kind: str, value: dict) -> None:
        """Durably record something of a step under way (the still target's reading before a transfer)."""
        ...

    def notes(self, idx: int) -> dict[str, dict]:
        """What :meth:`note` recorded for a step, by kind."""
        ...

    async def record_resume(self, idx: int, entry: dict) -> None:
        """Durably record how this run resumed at step ``idx`` (one entry per resume, however many there are)."""
        ...

    async def commit(self, idx: int, kind: str, result: dict, scan_file: Path | None = None,
                     scan_points: int = 0) -> None:
        """Commit a step's result (and its fsynced scan file) atomically."""
        ...


class _NoJournal:
    """The journal of a run outside the daemon: nothing is resumed (its scans are still written as it goes)."""

    committed: dict[int, dict] = {}

    async def run_step(self, idx: int, fn: Callable[[], Awaitable[T]]) -> T:
        return await fn()

    async def note(self, idx: int, kind: str, value: dict) -> None:
        return None

    def notes(self, idx: int) -> dict[str, dict]:
        return {}

    async def record_resume(self, idx: int, entry: dict) -> None:
        return None

    async def commit(self, idx: int, kind: str, result: dict, scan_file: Path | None = None,
                     scan_points: int = 0) -> None:
        return None


def installation_for_job(config: CellConfig, session: CellSession) -> Installation:
    """The mount transforms the stitch uses, per ``job.installation_source`` (``"truth"``: the simulation's
    surveyed mounts, as a perfect calibration file would give them)."""
    source = config.job.installation_source
    if source == "nominal":
        return Installation.nominal(config.installation)
    if source == "truth":
        sim = session.cell.simulation
        surveyed = None if sim is None else sim.surveyed_installation()
        if surveyed is None:
            raise JobError("installation_source = 'truth' needs the simulated cell (twins, not real drivers)")
        return surveyed
    path = config.job.calibration_file
    if path is None or not Path(path).is_file():
        raise JobError(f"installation_source = 'calibration' but no calibration file at {path}")
    return Installation.load(path)


class JobRunner:
    """Runs one plan on the cell of an open ``session`` into ``job_dir``: every motion through the session's
    gate, steps through ``journal`` (none: a run that cannot resume), what it measures told to the session's
    observer (the simulated cell's ground truth; none on a real cell)."""

    def __init__(
        self,
        session: CellSession,
        plan: Plan,
        config: CellConfig,
        job_dir: Path,
        progress: Callable[[JobProgress], None] | None = None,
        journal: StepJournal | None = None,
        worldmap: LocalWorldMap | ProcessWorldMap | None = None,
    ):
        self.cell = session.cell
        self.gate: MotionGate = session.gate
        self.plan = plan
        self.config = config
        self.job_dir = Path(job_dir)
        self.progress = progress or (lambda p: None)
        self.journal = journal or _NoJournal()
        self.observer: JobObserver | None = session.job_observer(self.job_dir.name, bool(self.journal.committed))
        self.installation = installation_for_job(config, session)
        self.worldmap = worldmap if worldmap is not None else LocalWorldMap(config.job.voxel_mm)
        self.T_W_C = np.eye(4)  # W is the tracker camera frame at its first station
        self.tracker_station = 0
        self.scans: list[ScanRecord] = []
        self.transfers: list[dict] = []
        self.correction: dict = {"enabled": False}
        self.last_still_T_C_T: np.ndarray | None = None  # last reading while the target has not moved since
        self.resume_log: list[dict] = []
        # with relocalisation on, W is placed in the plan's frame F at the start (the anchor: the inspection's
        # registration to CAD); the AGV is located after each drive where the plan has scanner poses to re-solve
        self.relocaliser = Relocaliser(config.arm, config.scanner, self.installation) if config.job.relocalise else None
        self.resolving = self.relocaliser is not None and any(
            isinstance(s, MoveArm) and s.T_F_S is not None for s in plan.steps)
        self.T_F_W: np.ndarray | None = None  # W in the plan's frame F (mm): None until measured
        self.T_F_V2: np.ndarray | None = None  # the measurement AGV in F as measured; None since it drove unmeasured
        self.planned_T_F_V2: np.ndarray | None = None  # where the plan (or, at the start, the odometry) puts it
        self.relocalisation: dict = {"enabled": self.resolving, "anchor": None, "located": [],
                                     "unresolved": [], "adjusted": [], "untracked": []}
        self.lift_mm = 0.0  # the lifting column's height (mm above the arm's mount) as last reported

    async def read_target(self) -> TrackerReading:
        """The target pose at rest, averaged over ``tracker.samples_per_reading`` readings."""
        return await read_at_rest(self.cell.tracker, self.config.tracker.samples_per_reading,
                                  self.config.tracker.timeout_s)

    async def run(self) -> JobResult:
        """Execute every step, then stitch and export. Raises :class:`JobError` on failure."""
        started = time.monotonic()
        (self.job_dir / "scans").mkdir(parents=True, exist_ok=True)
        total = len(self.plan.steps) + 1
        await self.cell.arm.enable()
        if self.cell.lift is not None:
            self.lift_mm = await self.cell.lift.height()
        resuming = bool(self.journal.committed)
        if self.relocaliser is not None and 0 not in self.journal.committed and not isinstance(
                self.plan.steps[0], MoveTracker):  # an opening tracker move redefines W: anchor after it
            await self._anchor(0)
        for i, step in enumerate(self.plan.steps):
            if i in self.journal.committed:
                await self._replay(step, self.journal.committed[i])
                continue
            if resuming:
                await self._reestablish(i, step)
                resuming = False
            self.progress(JobProgress(i, total, self._describe(step)))
            result, scan = await self.journal.run_step(i, lambda i=i, step=step: self._execute(i, step))
            await self.journal.commit(i, step.kind, result, *(scan or ()))
        measured_at = time.monotonic()  # the last step committed: from here the operator waits for the report
        self.progress(JobProgress(total - 1, total, "correcting the stitch, writing cloud and report"))
        finished = await self.worldmap.finish(self.snapshot(), started, measured_at)
        self.correction = finished.correction.section
        for s, T_W_S in zip(self.scans, finished.correction.poses, strict=True):
            s.T_W_S = T_W_S  # JobResult's records carry the final poses; report.json has both (finish.FinishedJob)
        self.progress(JobProgress(total, total, "done"))
        return JobResult(self.job_dir, self.job_dir / "cloud.ply", self.job_dir / "report.json", finished.report,
                         self.scans)

    async def _execute(self, i: int, step) -> tuple[dict, tuple[Path, int] | None]:
        """One step on the devices; returns its journal result and its scan file (path, points) if any."""
        if isinstance(step, MoveTracker):
            if not self.scans:
                return await self._relocate_tracker(step, i), None
            return await self._transfer(step, i), None
        if isinstance(step, MoveMeasure):
            pose = ChassisPose(step.x_mm, step.y_mm, step.heading_rad)
            self.last_still_T_C_T = None
            async with self.gate.motion(MEASURE_ROBOT):
                odo = await self.cell.measure_chassis.move_to(pose, self.config.measure_chassis.timeout_s)
            result = {"odometry": [odo.x_mm, odo.y_mm, odo.heading_rad]}
            if self.resolving:
                self.planned_T_F_V2 = F.planar_pose(step.x_mm, step.y_mm, step.heading_rad)
                self.T_F_V2 = None
                result |= self._relocalisation_state(located=await self._locate(i))
            return result, None
        if isinstance(step, MoveLift):
            return await self._move_lift(step), None
        if isinstance(step, MoveArm):
            self.last_still_T_C_T = None
            joints, extra = await self._arm_target(i, step)
            async with self.gate.motion(MEASURE_ROBOT):
                await self.cell.arm.move_joints(joints, self.config.arm.timeout_s)
            return {"joints_rad": joints.tolist(), **extra}, None
        try:
            record = await self._scan()
        except TargetNotVisible as e:  # e.g. a nearby view the plan's tracker cover did not check: go on
            return {"untracked": self._untracked(i, e.reason)}, None
        return _scan_result(record), (record.file, record.point_count)

    def _untracked(self, i: int, reason: str) -> dict:
        """A scan left out because the tracker could not see the target: the report entry (step, label, why)."""
        step = self.plan.steps[i]
        entry = {"step": i, "label": step.label if isinstance(step, Scan) else "", "reason": reason}
        log.warning("step %d (%s): scan left out, %s", i, entry["label"], reason)
        self.relocalisation["untracked"].append(entry)
        return entry

    async def _move_lift(self, step: MoveLift) -> dict:
        """Raise or lower the measurement AGV's lifting column, inside the measurement robot's motion gate."""
        if self.cell.lift is None:
            raise JobError("the plan moves a lifting column but this cell has none ([lift] enabled = false)")
        self.last_still_T_C_T = None
        async with self.gate.motion(MEASURE_ROBOT):
            self.lift_mm = await self.cell.lift.move_to(step.height_mm, self.config.lift.timeout_s)
        return {"height_mm": self.lift_mm}

    async def _replay(self, step, result: dict) -> None:
        """Rebuild the run's state from a step committed before a restart (no device is touched)."""
        if isinstance(step, MoveTracker) and result.get("relocation"):
            self.T_W_C = np.eye(4)
            self.last_still_T_C_T = None
            self._restore_relocalisation(result)
        elif isinstance(step, MoveTracker):
            self.T_W_C = np.array(result["T_W_C"])
            self.tracker_station = result["station"]
            self.transfers.append(result["transfer"])
            self.last_still_T_C_T = np.array(result["after"])
        elif isinstance(step, MoveLift):
            self.last_still_T_C_T = None
            self.lift_mm = result["height_mm"]
        elif isinstance(step, (MoveMeasure, MoveArm)):
            self.last_still_T_C_T = None
            self._restore_relocalisation(result)
        elif isinstance(step, Scan) and "untracked" in result:
            self.relocalisation["untracked"].append(result["untracked"])
        elif isinstance(step, Scan):
            record = _scan_from_result(result, self.job_dir)
            self.scans.append(record)
            self.last_still_T_C_T = record.reading.T_C_T
            await self.worldmap.add_scan(record.file, record.T_W_S)

    async def _reestablish(self, i: int, step) -> None:
        """After a restart, before moving anything: a fresh target reading. Where the target has not moved
        since the last journaled reading and the tracker is not mid-transfer, the two must agree; if not,
        the tracker was moved while the daemon was down and its frame is re-established from the fresh one."""
        entry: dict = {"step": i, "kind": step.kind}
        try:
            fresh = await self.read_target()
        except TargetNotVisible as e:
            entry["fresh_reading"] = f"target not visible: {e.reason}"
            self.resume_log.append(entry)
            log.warning("resume at step %d: %s", i, entry["fresh_reading"])
            await self.journal.record_resume(i, entry)
            return
        entry["T_C_T"] = fresh.T_C_T.tolist()
        if self.last_still_T_C_T is not None and not isinstance(step, MoveTracker):
            d_mm, d_rad = F.pose_error(fresh.T_C_T, self.last_still_T_C_T)
            entry |= {"deviation_mm": d_mm, "deviation_deg": float(np.degrees(d_rad))}
            if d_mm > RESUME_TOLERANCE_MM or np.degrees(d_rad) > RESUME_TOLERANCE_DEG:
                T_W_T = self.T_W_C @ self.last_still_T_C_T
                self.T_W_C = F.coordinate_transfer(self.T_W_C, self.last_still_T_C_T, fresh.T_C_T)
                entry["reestablished"] = True
                log.warning("resume at step %d: tracker moved while down (%.3f mm); frame re-established from "
                            "the still target at %s", i, d_mm, T_W_T[:3, 3].round(3).tolist())
        self.resume_log.append(entry)
        await self.journal.record_resume(i, entry)

    @staticmethod
    def _describe(step) -> str:
        return {
            "move_tracker": "coordinate transfer: moving the tracking robot",
            "move_measure": "moving the measurement robot",
            "move_lift": "moving the lifting column",
            "move_arm": "moving the arm",
            "scan": "scanning",
        }[step.kind]

    async def _anchor(self, i: int) -> None:
        """Place W in the plan's frame F from one target reading (Eq. 5), the measurement AGV standing where it
        was last measured or, before that, where its odometry says (the plan's frame is the odometry frame).
        Journaled as a note of step ``i``, so a resumed job keeps it; the target unseen leaves W unplaced (the
        first AGV station measured then places it, taken as planned)."""
        if self.planned_T_F_V2 is None:
            odo = await self.cell.measure_chassis.odometry()
            self.planned_T_F_V2 = F.planar_pose(odo.x_mm, odo.y_mm, odo.heading_rad)
        noted = self.journal.notes(i).get("anchor")
        if noted is None:
            try:
                reading = await self.read_target()
            except TargetNotVisible as e:
                self.T_F_W = None
                self.relocalisation["anchor"] = {"step": i, "placed": False, "reason": e.reason}
                log.info("world not placed in the plan's frame at step %d: %s", i, e.reason)
                return
            T_F_V2 = self.planned_T_F_V2 if self.T_F_V2 is None else self.T_F_V2
            T_W_V2 = self.relocaliser.agv_in_world(self.T_W_C @ reading.T_C_T, await self.cell.arm.joints(),
                                                   self.lift_mm)
            noted = {"step": i, "placed": True, "source": "measurement AGV where its odometry says"
                     if self.T_F_V2 is None else "measurement AGV where last measured",
                     "T_F_W": (T_F_V2 @ F.invert(T_W_V2)).tolist(), "T_F_V2": T_F_V2.tolist()}
            await self.journal.note(i, "anchor", noted)
        self.T_F_W, self.T_F_V2 = np.array(noted["T_F_W"]), np.array(noted["T_F_V2"])
        self.relocalisation["anchor"] = {k: noted[k] for k in ("step", "placed", "source")}

    async def _locate(self, i: int) -> dict | None:
        """Where the measurement AGV stands now (``self.T_F_V2``, Eq. 5), from a reading at the arm's current
        pose; None (and ``T_F_V2`` unknown) when the tracker cannot see the target from there."""
        try:
            reading = await self.read_target()
        except TargetNotVisible as e:
            log.debug("step %d: measurement AGV not located from this arm pose: %s", i, e.reason)
            return None
        T_W_V2 = self.relocaliser.agv_in_world(self.T_W_C @ reading.T_C_T, await self.cell.arm.joints(),
                                               self.lift_mm)
        planned = self.planned_T_F_V2
        if self.T_F_W is None:
            self.T_F_W = planned @ F.invert(T_W_V2)
            self.relocalisation["anchor"] = {"step": i, "placed": True,
                                             "source": "first measured AGV station, taken as planned"}
        self.T_F_V2 = self.T_F_W @ T_W_V2
        off_mm, off_rad = F.pose_error(self.T_F_V2, planned)
        entry = {"step": i, "off_plan_mm": off_mm, "off_plan_deg": float(np.degrees(off_rad))}
        if self.observer is not None:
            self.observer.agv_located(i, self.T_F_V2)
        log.info("measurement AGV located %.1f mm / %.2f deg off its planned station", off_mm, entry["off_plan_deg"])
        return entry

    async def _arm_target(self, i: int, step: MoveArm) -> tuple[np.ndarray, dict]:
        """The joints of a ``move_arm`` step: re-solved for its planned scanner pose where the AGV was measured
        to stand, else (no ``T_F_S``, relocalisation off) the plan's. The journal result's extra fields."""
        planned = np.array(step.joints_rad)
        if not self.resolving or step.T_F_S is None:
            return planned, {}
        located = None
        if self.T_F_V2 is None and self.planned_T_F_V2 is not None:  # not seen from the travel pose: from here
            async with self.gate.motion(MEASURE_ROBOT):
                await self.cell.arm.move_joints(planned, self.config.arm.timeout_s)
            located = await self._locate(i)
        if self.T_F_V2 is None:
            return planned, self._relocalisation_state(located, self._unresolved(
                i, "measurement AGV not located: the tracker sees the target from none of its poses since it drove"))
        q, changed = self.relocaliser.resolve(self.T_F_V2, np.array(step.T_F_S), planned, self.lift_mm)
        if q is None:
            return planned, self._relocalisation_state(located, self._unresolved(
                i, "planned scanner pose and its nearby views out of the arm's reach from where the AGV stands; "
                "the plan's joints used"))
        adjusted = None
        if changed:
            adjusted = {"step": i, "scan": len(self.scans), "view": changed}
            log.info("step %d (scan %d): planned pose out of reach from where the AGV stands; view %s", i,
                     len(self.scans), changed)
        return q, self._relocalisation_state(located, adjusted=adjusted)

    def _unresolved(self, i: int, reason: str) -> dict:
        """A report entry for a scan pose not re-solved: the step, the scan it serves and why."""
        label = next((s.label for s in self.plan.steps[i + 1:] if isinstance(s, Scan)), "")
        log.warning("step %d (scan %d, %s): %s", i, len(self.scans), label, reason)
        return {"step": i, "scan": len(self.scans), "label": label, "reason": reason}

    def _relocalisation_state(self, located: dict | None = None, unresolved: dict | None = None,
                              adjusted: dict | None = None) -> dict:
        """The step's journal fields that let a resumed job rebuild the relocalisation state and report."""
        entries = {"located": located, "unresolved": unresolved, "adjusted": adjusted}
        for key, entry in entries.items():
            if entry is not None:
                self.relocalisation[key].append(entry)
        matrix = {k: None if v is None else v.tolist()
                  for k, v in (("T_F_W", self.T_F_W), ("T_F_V2", self.T_F_V2), ("planned_T_F_V2", self.planned_T_F_V2))}
        return {"relocalisation": {**matrix, "anchor": self.relocalisation["anchor"], **entries}}

    def _restore_relocalisation(self, result: dict) -> None:
        """Inverse of :meth:`_relocalisation_state` for a replayed step."""
        state = result.get("relocalisation")
        if state is None:
            return
        self.T_F_W, self.T_F_V2, self.planned_T_F_V2 = (None if state[k] is None else np.array(state[k])
                                                         for k in ("T_F_W", "T_F_V2", "planned_T_F_V2"))
        self.relocalisation["anchor"] = state["anchor"]
        for key in ("located", "unresolved", "adjusted"):
            if state.get(key) is not None:
                self.relocalisation[key].append(state[key])

    async def _relocate_tracker(self, step: MoveTracker, i: int) -> dict:
        """A tracker move before the first scan: no transfer, W becomes the camera frame where it now stands."""
        async with self.gate.motion(TRACKING_ROBOT):
            odo = await self.cell.tracking_chassis.move_to(
                ChassisPose(step.x_mm, step.y_mm, step.heading_rad), self.config.tracking_chassis.timeout_s
            )
        self.T_W_C = np.eye(4)
        self.last_still_T_C_T = None
        if self.observer is not None:
            self.observer.world_defined()
        log.info("tracker relocated before the first scan: the world frame is its camera frame there")
        result = {"relocation": True, "odometry": [odo.x_mm, odo.y_mm, odo.heading_rad]}
        if self.relocaliser is not None:
            await self._anchor(i)
            result |= self._relocalisation_state()
        return result

    async def _transfer(self, step: MoveTracker, i: int = -1) -> dict:
        """Eq. 2: read the still target, move the tracker, read it again, re-place the tracker in W.

        The reading before the move (and the tracking chassis' odometry) is journaled before the tracker moves,
        so a transfer interrupted by a crash, a safety stop or a device fault completes from it (the target stays
        still meanwhile), and one of a job that fails or is cancelled is undone (:func:`return_from_transfer`).
        The transfer's entry carries its error prior for the pose graph: the still target's origin in W and the
        covariance of both readings (``uncertainty.transfer_covariance``)."""
        noted = self.journal.notes(i).get("before")
        if noted is not None:
            before_T_C_T, before_cov = np.array(noted["T_C_T"]), np.array(noted["covariance"])
        else:
            before = await self.read_target()
            before_T_C_T, before_cov = before.T_C_T, before.covariance
            odo = await self.cell.tracking_chassis.odometry()  # where an abandoned transfer returns the tracker
            await self.journal.note(i, "before", {"T_C_T": before_T_C_T.tolist(), "covariance": before_cov.tolist(),
                                                  "odometry": [odo.x_mm, odo.y_mm, odo.heading_rad]})
        async with self.gate.motion(TRACKING_ROBOT):
            odo = await self.cell.tracking_chassis.move_to(
                ChassisPose(step.x_mm, step.y_mm, step.heading_rad), self.config.tracking_chassis.timeout_s
            )
        after = await self.read_target()
        T_W_C_before = self.T_W_C
        self.T_W_C = F.coordinate_transfer(self.T_W_C, before_T_C_T, after.T_C_T)
        self.last_still_T_C_T = after.T_C_T
        self.tracker_station += 1
        entry = {"station": self.tracker_station, "after_scan": len(self.scans),
                 "target_W_mm": (T_W_C_before @ before_T_C_T)[:3, 3].tolist(),
                 "covariance": transfer_covariance(T_W_C_before, before_cov, self.T_W_C, after.covariance).tolist()}
        if self.observer is not None:
            self.observer.tracker_transferred(self.tracker_station, self.T_W_C)
        self.transfers.append(entry)
        log.info("coordinate transfer", extra={"station": self.tracker_station})
        return {"T_W_C": self.T_W_C.tolist(), "station": self.tracker_station, "transfer": entry,
                "before": before_T_C_T.tolist(), "after": after.T_C_T.tolist(),
                "odometry": [odo.x_mm, odo.y_mm, odo.heading_rad]}

    async def _scan(self) -> ScanRecord:
        """Capture and read at rest, persist raw data first, then stitch into the world map."""
        frame = await self.cell.scanner.capture(self.config.scanner.timeout_s)
        reading = await self.read_target()
        joints = await self.cell.arm.joints()
        index = len(self.scans)
        file = self.job_dir / "scans" / f"scan-{index:04d}.npz"
        arrays = {  # written (points as float32) and stitched where the map lives, not on the event loop
            "points_S_mm": frame.points_mm,
            "T_C_T": reading.T_C_T,
            "tracker_covariance": reading.covariance,
            "joints_rad": joints,
            "scan_timestamp_s": np.array(frame.timestamp_s),
            "tracker_timestamp_s": np.array(reading.timestamp_s),
            "T_W_C": self.T_W_C,
        }
        if frame.normals is not None:
            arrays["normals_S"] = frame.normals
        T_W_S = F.compose(self.T_W_C, reading.T_C_T, self.installation.T_T_S)
        await self.worldmap.add_scan(  # the file is durable before this returns; its pairs registered meanwhile
            file, T_W_S, arrays, pairs={"correction": self.config.correction, "station": self.tracker_station,
                                        "transfers": list(self.transfers), "T_T_S": self.installation.T_T_S})
        if self.observer is not None:
            self.observer.scan_measured(index)
        record = ScanRecord(index, self.tracker_station, file, reading, joints, self.T_W_C.copy(), T_W_S,
                            len(frame.points_mm))
        self.scans.append(record)
        self.last_still_T_C_T = reading.T_C_T
        return record

    def snapshot(self, scans: list[ScanRecord] | None = None) -> JobSnapshot:
        """The job's state for its end-of-job work (correction, report, exports) where the map lives; ``scans``
        (default: all) are the ones that work sees."""
        scorer = self.observer.scorer() if self.observer is not None else None
        return JobSnapshot(self.job_dir, self.plan, self.config, self.installation, list(scans or self.scans),
                           list(self.transfers), dict(self.correction), scorer, T_F_W=self.T_F_W,
                           relocalisation=dict(self.relocalisation))

    async def _export(self, seconds: float, measured_at: float) -> JobResult:
        """``cloud.ply``, ``report.json`` and the inspection exports, written where the map lives
        (``measured_at``: ``time.monotonic()`` when the last step was committed)."""
        report = await self.worldmap.run(export, self.snapshot(), seconds, measured_at)
        return JobResult(self.job_dir, self.job_dir / "cloud.ply", self.job_dir / "report.json", report, self.scans)


def _scan_result(r: ScanRecord) -> dict:
    """A scan's journal entry: everything :class:`ScanRecord` holds except the points (in its file)."""
    return {
        "index": r.index, "station": r.tracker_station, "file": r.file.name, "points": r.point_count,
        "T_C_T": r.reading.T_C_T.tolist(), "covariance": r.reading.covariance.tolist(),
        "timestamp_s": r.reading.timestamp_s, "frame_number": r.reading.frame_number,
        "joints_rad": np.asarray(r.joints_rad).tolist(), "T_W_C": r.T_W_C.tolist(), "T_W_S": r.T_W_S.tolist(),
    }


def _scan_from_result(d: dict, job_dir: Path) -> ScanRecord:
    """Inverse of :func:`_scan_result`."""
    reading = TrackerReading(np.array(d["T_C_T"]), np.array(d["covariance"]), d["timestamp_s"], d["frame_number"])
    return ScanRecord(d["index"], d["station"], job_dir / "scans" / d["file"], reading, np.array(d["joints_rad"]),
                      np.array(d["T_W_C"]), np.array(d["T_W_S"]), d["points"])


async def return_from_transfer(session: CellSession, plan: Plan, committed: set[int],
                               notes: Callable[[int], dict[str, dict]], config: CellConfig) -> bool:
    """Undo the half transfer of an abandoned (failed, cancelled) job: where its first uncommitted step is a
    ``move_tracker`` whose reading before the move was noted, drive the tracking robot back to the odometry noted
    with it, through the gate. Returns whether it drove; the next job then finds the tracker where it stood."""
    i = next((k for k in range(len(plan.steps)) if k not in committed), None)
    if i is None or not isinstance(plan.steps[i], MoveTracker):
        return False
    odo = notes(i).get("before", {}).get("odometry")
    if odo is None:
        return False
    async with session.gate.motion(TRACKING_ROBOT):
        await session.cell.tracking_chassis.move_to(ChassisPose(*odo), config.tracking_chassis.timeout_s)
    log.warning("abandoned transfer of step %d undone: the tracking robot is back at %s", i, odo)
    return True

