"""The runner's AGV relocalisation: W placed in the plan's frame F, the measurement AGV located after each drive,
and the arm re-solved for each ``move_arm`` step's planned scanner pose from where the AGV stands.

The anchor (Eq. 5, the in-job inspection's registration to CAD) is one target reading at the start, the AGV taken
where its odometry (or its last measurement) puts it. After a drive the AGV is located from a reading at the arm's
pose (:mod:`tandemscan.pipeline.stitching.relocalise`); a pose out of reach from there, or an AGV the tracker sees
from none of its poses since it drove, is scanned with the plan's joints and reported. These functions read the
devices and return records and states (:mod:`tandemscan.daemon.jobs.records`, :mod:`tandemscan.daemon.jobs.run_state`);
they change nothing. Frames: W the job's world frame, F the plan's, V2 the measurement AGV; mm, rad.
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, replace

import numpy as np
from tandemscan.daemon.cell.motion import Robot
from tandemscan.daemon.cell.observer import JobObserver
from tandemscan.daemon.cell.session import MotionGate
from tandemscan.daemon.jobs.records import AnchorEntry, RelocalisationEntry
from tandemscan.daemon.jobs.run_state import RelocalisationState, RunState
from tandemscan.daemon.jobs.step_journal import StepJournal
from tandemscan.drivers.errors import TargetNotVisible
from tandemscan.drivers.interfaces import TrackerReading
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.planning.plan import MoveArm, Plan, Scan
from tandemscan.pipeline.stitching.relocalise import Relocaliser

log = logging.getLogger(__name__)


@dataclass
class AgvRelocalisation:
    """The relocalisation of one job: ``relocaliser`` on the cell's devices, readings by ``read_target`` (the
    target at rest), arm moves through ``gate``, the anchor noted in ``journal``."""

    relocaliser: Relocaliser
    cell: object
    gate: MotionGate
    arm_timeout_s: float
    journal: StepJournal
    plan: Plan
    read_target: Callable[[], Awaitable[TrackerReading]]
    observer: JobObserver | None = None

    async def _agv_in_world(self, state: RunState, reading: TrackerReading) -> np.ndarray:
        """``T_W_V2`` (mm) from a target reading at the arm's current joints."""
        return self.relocaliser.agv_in_world(state.T_W_C @ reading.T_C_T, await self.cell.arm.joints(),
                                             state.lift_mm)

    async def anchor(self, i: int, state: RunState) -> AnchorEntry:
        """Place W in F from one target reading (Eq. 5), the AGV standing where it was last measured or, before
        that, where its odometry says (the plan's frame is the odometry frame). Noted under step ``i``, so a
        resumed job keeps it; the target unseen leaves W unplaced (the first AGV station measured places it)."""
        planned = state.relocalisation.planned_T_F_V2
        if planned is None:
            odo = await self.cell.measure_chassis.odometry()
            planned = F.planar_pose(odo.x_mm, odo.y_mm, odo.heading_rad)
        noted = self.journal.notes(i).get("anchor")
        if noted is not None:
            return AnchorEntry.from_json(noted, planned)
        try:
            reading = await self.read_target()
        except TargetNotVisible as e:
            log.info("world not placed in the plan's frame at step %d: %s", i, e.reason)
            return AnchorEntry(i, False, reason=e.reason, planned_T_F_V2=planned)
        measured = state.relocalisation.T_F_V2
        T_F_V2 = planned if measured is None else measured
        T_W_V2 = await self._agv_in_world(state, reading)
        entry = AnchorEntry(i, True, "measurement AGV where its odometry says" if measured is None
                            else "measurement AGV where last measured", None, T_F_V2 @ F.invert(T_W_V2), T_F_V2,
                            planned)
        await self.journal.note(i, "anchor", entry.to_json())
        return entry

    async def locate(self, i: int, state: RunState) -> tuple[dict | None, RelocalisationState]:
        """Where the AGV stands now (``T_F_V2``, Eq. 5), from a reading at the arm's current pose: the report's
        entry and the relocalisation state; no entry (and ``T_F_V2`` unchanged) when the tracker cannot see the
        target from there. The first station located places W where W is not placed yet."""
        reloc = state.relocalisation
        try:
            reading = await self.read_target()
        except TargetNotVisible as e:
            log.debug("step %d: measurement AGV not located from this arm pose: %s", i, e.reason)
            return None, reloc
        T_W_V2 = await self._agv_in_world(state, reading)
        planned = reloc.planned_T_F_V2
        if reloc.T_F_W is None:
            reloc = replace(reloc, T_F_W=planned @ F.invert(T_W_V2), anchor={
                "step": i, "placed": True, "source": "first measured AGV station, taken as planned"})
        reloc = replace(reloc, T_F_V2=reloc.T_F_W @ T_W_V2)
        off_mm, off_rad = F.pose_error(reloc.T_F_V2, planned)
        entry = {"step": i, "off_plan_mm": off_mm, "off_plan_deg": float(np.degrees(off_rad))}
        if self.observer is not None:
            self.observer.agv_located(i, reloc.T_F_V2)
        log.info("measurement AGV located %.1f mm / %.2f deg off its planned station", off_mm, entry["off_plan_deg"])
        return entry, reloc

    async def after_drive(self, i: int, state: RunState, planned_T_F_V2: np.ndarray) -> RelocalisationEntry:
        """A drive of the AGV to ``planned_T_F_V2`` (mm, in F): located from the arm's pose where it can be."""
        reloc = replace(state.relocalisation, planned_T_F_V2=planned_T_F_V2, T_F_V2=None)
        located, reloc = await self.locate(i, replace(state, relocalisation=reloc))
        return reloc.entry(located=located)

    async def arm_target(self, i: int, step: MoveArm, state: RunState) -> tuple[np.ndarray, RelocalisationEntry]:
        """The joints of a ``move_arm`` step with a planned scanner pose ``T_F_S``, re-solved where the AGV was
        measured to stand (located from the plan's joints first where it was not seen since it drove), and the
        step's relocalisation entry; the plan's joints where that cannot be done (reported)."""
        planned = np.array(step.joints_rad)
        reloc, located = state.relocalisation, None
        if reloc.T_F_V2 is None and reloc.planned_T_F_V2 is not None:  # not seen from the travel pose: from here
            async with self.gate.motion(Robot.MEASURE) as robot:
                await robot.arm.move_joints(planned, self.arm_timeout_s)
            located, reloc = await self.locate(i, state)
        if reloc.T_F_V2 is None:
            return planned, reloc.entry(located, self._unresolved(i, state, "measurement AGV not located: the "
                                        "tracker sees the target from none of its poses since it drove"))
        q, changed = self.relocaliser.resolve(reloc.T_F_V2, np.array(step.T_F_S), planned, state.lift_mm)
        if q is None:
            return planned, reloc.entry(located, self._unresolved(
                i, state, "planned scanner pose and its nearby views out of the arm's reach from where the AGV "
                "stands; the plan's joints used"))
        adjusted = None
        if changed:
            adjusted = {"step": i, "scan": len(state.scans), "view": changed}
            log.info("step %d (scan %d): planned pose out of reach from where the AGV stands; view %s", i,
                     len(state.scans), changed)
        return q, reloc.entry(located, adjusted=adjusted)

    def _unresolved(self, i: int, state: RunState, reason: str) -> dict:
        """A report entry for a scan pose not re-solved: the step, the scan it serves and why."""
        label = next((s.label for s in self.plan.steps[i + 1:] if isinstance(s, Scan)), "")
        log.warning("step %d (scan %d, %s): %s", i, len(state.scans), label, reason)
        return {"step": i, "scan": len(state.scans), "label": label, "reason": reason}
