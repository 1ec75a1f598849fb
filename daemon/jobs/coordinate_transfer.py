"""Where the tracker camera stands in the job's world frame W: the coordinate transfer (Eq. 2), its check at a
resume, and undoing a half transfer of an abandoned job.

A transfer reads the still target before and after the tracker moves; ``T_W_C`` (mm) follows from the two
readings (:func:`tandemscan.pipeline.geometry.frames.coordinate_transfer`). With ``[tracker] transfer_arm_poses``
K > 1 the arm (its AGV standing still) carries the target through K poses on each side, the same joints
replayed after the tracker moved, and ``T_W_C`` follows from the K pairs
(:func:`~tandemscan.pipeline.geometry.frames.coordinate_transfer_poses`): the target positions over the arm's
reach fix the new station's rotation far better than one target's orientation (docs/architecture.md,
"Coordinate transfers"). The poses are the plan's scan poses at the transfer's AGV station, chosen spread out
and predicted visible from both tracker stations; one out of reach or found hidden is left out, logged and
listed in the transfer's record. At a resume a fresh reading of the still target must agree with the last
journaled one; where it does not, the tracker was moved while the daemon was down and its frame is
re-established the same way. Frames: W the job's world frame, C the tracker camera, T the target, E the flange,
B the arm base, V1 the tracking chassis (``docs/architecture.md``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from tandemscan.config.models import CellConfig, TrackerConfig
from tandemscan.daemon.cell.motion import Robot
from tandemscan.daemon.cell.session import CellSession, MotionGate
from tandemscan.daemon.cell.tracker_reading import read_for_transfer
from tandemscan.daemon.jobs.records import Odometry, TransferRecord
from tandemscan.daemon.jobs.run_state import RunState
from tandemscan.drivers.errors import TargetNotVisible
from tandemscan.drivers.interfaces import ChassisPose, TrackerReading
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.kinematics import ArmKinematics
from tandemscan.pipeline.geometry.uncertainty import arm_repeatability_covariance, transfer_covariance
from tandemscan.pipeline.planning.ik import default_ik
from tandemscan.pipeline.planning.plan import MoveArm, MoveLift, MoveMeasure, MoveTracker, Plan, Scan
from tandemscan.pipeline.stitching.installation import Installation

if TYPE_CHECKING:
    from tandemscan.daemon.cell.devices import Cell
    from tandemscan.daemon.jobs.step_journal import StepJournal

log = logging.getLogger(__name__)

# A fresh reading at resume that differs more than this from the journaled one (target still) means the
# tracker was moved while the daemon was down: its frame is then re-established from the fresh reading.
RESUME_TOLERANCE_MM = 0.5
RESUME_TOLERANCE_DEG = 0.05


def transfer_record(state: RunState, before_T_C_T: np.ndarray, before_covariance: np.ndarray,
                    after: TrackerReading, odometry: Odometry) -> TransferRecord:
    """The transfer from the still target read before the move (``T_C_T`` mm, 6x6 covariance) and after it: the
    tracker's next station, its camera in W and the pose graph's prior (the target's origin in W, the covariance
    of both readings, ``uncertainty.transfer_covariance``)."""
    T_W_C = F.coordinate_transfer(state.T_W_C, before_T_C_T, after.T_C_T)
    return TransferRecord(
        station=state.tracker_station + 1, after_scan=len(state.scans),
        target_W_mm=(state.T_W_C @ before_T_C_T)[:3, 3],
        covariance=transfer_covariance(state.T_W_C, before_covariance, T_W_C, after.covariance),
        T_W_C=T_W_C, before_T_C_T=before_T_C_T, after_T_C_T=after.T_C_T, odometry=odometry)


def poses_transfer_record(state: RunState, before: list[PoseReading | None], after: list[PoseReading | None],
                          odometry: Odometry, config: CellConfig, installation: Installation,
                          dropped: list[dict]) -> TransferRecord:
    """The transfer over several arm poses: ``before[k]`` and ``after[k]`` read at the same pose (None: hidden,
    the pair left out; pair 0 the transfer's own pose, where the arm ends). The record's ``T_W_C`` and prior
    (the targets' centroid in W, the estimate's 6x6 covariance about it) are :func:`pose_transfer`'s; it lists
    the pairs used, the count requested (``tracker.transfer_arm_poses``) and the poses ``dropped``."""
    requested = config.tracker.transfer_arm_poses
    kept = [k for k, (b, a) in enumerate(zip(before, after, strict=True)) if b is not None and a is not None]
    pairs = [(before[k], after[k]) for k in kept]
    est = pose_transfer(state.T_W_C, [b for b, _ in pairs], [a for _, a in pairs],
                        [k != len(before) - 1 for k in kept], config, installation)
    used = tuple({"joints_rad": None if b.joints_rad is None else b.joints_rad.tolist(), "before": b.T_C_T.tolist(),
                  "after": a.T_C_T.tolist()} for b, a in pairs)
    if len(pairs) < requested:
        log.warning("coordinate transfer over %d of %d arm poses (%s)", len(pairs), requested,
                    "; ".join(d["reason"] for d in dropped) or "no more candidates")
    return TransferRecord(
        station=state.tracker_station + 1, after_scan=len(state.scans), target_W_mm=est.centre_mm,
        covariance=est.covariance, T_W_C=est.T_W_C, before_T_C_T=pairs[0][0].T_C_T, after_T_C_T=pairs[0][1].T_C_T,
        odometry=odometry, arm_poses=used, arm_poses_requested=requested, arm_poses_dropped=tuple(dropped))


@dataclass(frozen=True)
class PoseReading:
    """The still target read (averaged, ``T_C_T`` mm and its 6x6 covariance in camera axes) at one arm pose of a
    transfer (``joints_rad``; None: where the arm stood, not commanded)."""

    joints_rad: np.ndarray | None
    T_C_T: np.ndarray
    covariance: np.ndarray

    def to_json(self) -> dict:
        return {"joints_rad": None if self.joints_rad is None else np.asarray(self.joints_rad).tolist(),
                "T_C_T": self.T_C_T.tolist(), "covariance": self.covariance.tolist()}

    @classmethod
    def from_json(cls, d: dict) -> PoseReading:
        q = d.get("joints_rad")
        return cls(None if q is None else np.array(q, float), np.array(d["T_C_T"], float),
                   np.array(d["covariance"], float))


def _block(plan: Plan, i: int) -> range:
    """The steps around step ``i`` during which the measurement AGV and its column stand still."""
    stops = (MoveMeasure, MoveLift)
    start = i
    while start > 0 and not isinstance(plan.steps[start - 1], stops):
        start -= 1
    end = i + 1
    while end < len(plan.steps) and not isinstance(plan.steps[end], stops):
        end += 1
    return range(start, end)


def _arm_joints(plan: Plan, j: int, committed: Mapping[int, dict]) -> np.ndarray:
    """The joints (rad) of ``move_arm`` step ``j``: committed ones (re-solved where the job relocalises), else the
    plan's."""
    done = committed.get(j)
    return np.array(done["joints_rad"] if done and "joints_rad" in done else plan.steps[j].joints_rad, float)


def transfer_joints(plan: Plan, i: int, committed: Mapping[int, dict], current: np.ndarray | None = None
                    ) -> tuple[np.ndarray | None, list[np.ndarray]]:
    """Where the arm stands at the transfer of step ``i`` (the last arm move before it: its committed joints,
    re-solved where the job relocalises; else ``current``, the arm's joints now, else the plan's; None when the
    arm has not moved) and the other scan poses of the plan at the same AGV station and column height (each a
    ``move_arm`` followed by a scan; rad): the poses the transfer may carry the target through. The committed
    joints come first: a transfer restarted after a crash between its poses finds the arm at one of them."""
    block = _block(plan, i)
    moves = [j for j in block if isinstance(plan.steps[j], MoveArm)]
    before = [j for j in moves if j < i]
    q0 = None
    if before:
        last = before[-1]
        q0 = _arm_joints(plan, last, committed) if last in committed or current is None else np.asarray(current, float)
    scans = [_arm_joints(plan, j, committed) for j in moves
             if j + 1 < len(plan.steps) and isinstance(plan.steps[j + 1], Scan)]
    others: list[np.ndarray] = []
    for q in scans:
        if (q0 is None or not np.allclose(q, q0)) and not any(np.allclose(q, o) for o in others):
            others.append(q)
    return q0, others


def fallback_joints(plan: Plan, i: int, committed: Mapping[int, dict], around: list[np.ndarray],
                    others: list[np.ndarray]) -> list[np.ndarray]:
    """Where the transfer of step ``i`` reads the target when it is hidden at the transfer's own pose, in order:
    the plan's alternatives of the step (scans whose target both tracker stations see past the part; the joints
    of the arm move before each, committed where re-solved), then ``around`` (the scanner moved across its view
    from the own pose, :func:`offset_poses`: the target near where the planner checked it), then the station's
    other scan poses ``others`` (rad), each once."""
    at = {s.label: j for j, s in enumerate(plan.steps) if isinstance(s, Scan) and s.label}
    out = [_arm_joints(plan, at[label] - 1, committed) for label in plan.steps[i].alternatives
           if at.get(label, 0) > 0 and isinstance(plan.steps[at[label] - 1], MoveArm)]
    for q in [*around, *others]:
        if not any(np.allclose(q, p) for p in out):
            out.append(q)
    return out


# The target predicted this far (deg) inside the edges of the tracker's view and target cone: the prediction
# (kinematics, installation, odometry) errs by far less, and the part's shadow is found when read.
_VIEW_MARGIN_DEG = 1.0
# An extra pose whose joints turn farther than this (rad) from the transfer's own is left out: a joint move that
# large would swing the scanner through unplanned space.
_MAX_JOINT_TRAVEL_RAD = np.radians(60.0)


def _visible(T_C_T: np.ndarray, tracker: TrackerConfig) -> bool:
    """The tracker model's field of view, range and target cone, ``_VIEW_MARGIN_DEG`` inside their edges (mm,
    camera)."""
    p = T_C_T[:3, 3]
    d = float(np.linalg.norm(p))
    if d > tracker.range_max_mm or p[2] <= 0:
        return False
    h, v = np.degrees(np.arctan2(abs(p[0]), p[2])), np.degrees(np.arctan2(abs(p[1]), p[2]))
    facing = np.degrees(np.arccos(np.clip(-T_C_T[:3, 2] @ p / d, -1, 1)))
    m = _VIEW_MARGIN_DEG
    return bool(h <= tracker.fov_horizontal_deg / 2 - m and v <= tracker.fov_vertical_deg / 2 - m
                and facing <= tracker.target_view_cone_deg - m)


def offset_poses(q0: np.ndarray, config: CellConfig, installation: Installation) -> list[np.ndarray]:
    """Joints (rad) that move the scanner, from its pose at ``q0``, by ``tracker.transfer_arm_reach_mm`` across
    its view (its own x and y, the view axis and orientation kept: the standoff to the part and the target's
    facing stay), to the 8 points of a square around it; those the arm cannot reach near ``q0`` are left out."""
    reach = config.tracker.transfer_arm_reach_mm
    ik = default_ik(config.arm)
    T_B_S = ArmKinematics(config.arm).forward(q0) @ installation.T_E_S
    T_S_E = F.invert(installation.T_E_S)
    out = []
    for dx, dy in ((1, 1), (-1, -1), (1, -1), (-1, 1), (1, 0), (-1, 0), (0, 1), (0, -1)):
        shift = F.make_transform(np.eye(3), (dx * reach, dy * reach, 0.0))
        q = ik(T_B_S @ shift @ T_S_E, q0)
        if q is not None and np.max(np.abs(q - q0)) <= _MAX_JOINT_TRAVEL_RAD:
            out.append(np.asarray(q, float))
    return out


def camera_move(installation: Installation, odometry: Odometry, step: MoveTracker) -> np.ndarray:
    """``T_C_Cn``: the tracker camera at the station ``step`` drives to, in the camera frame where it stands (the
    tracking chassis' odometry ``odometry``, mm, rad)."""
    T_V1_C = installation.T_V1_C
    return F.compose(F.invert(T_V1_C), F.invert(F.planar_pose(*odometry)),
                     F.planar_pose(step.x_mm, step.y_mm, step.heading_rad), T_V1_C)


def choose_transfer_poses(q0: np.ndarray, others: list[np.ndarray], T_C_T0: np.ndarray, T_C_Cn: np.ndarray,
                          count: int, config: CellConfig, installation: Installation
                          ) -> tuple[list[np.ndarray], list[dict]]:
    """Up to ``count - 1`` poses (joints rad) to read the target at besides ``q0``, where the target reads
    ``T_C_T0`` (mm) now: of ``others`` (the plan's scan poses here) and :func:`offset_poses`, those within the
    joint limits whose target is predicted inside the tracker's view from the station now and from the next one,
    ``T_C_Cn`` in the camera frame now (:func:`camera_move`; the arm's kinematics and the installation predict
    the target; the part's shadow is found when read), chosen one by one farthest from those chosen (the widest
    baseline). Returns the poses in reading order and the candidates left out (joints and why)."""
    kin = ArmKinematics(config.arm)
    T_E_T = installation.T_E_T
    T_T0_B = F.invert(kin.forward(q0) @ T_E_T)
    left_out, usable, positions = [], [], []
    for q in [*offset_poses(q0, config, installation), *others]:
        if not kin.within_limits(q):
            left_out.append({"joints_rad": q.tolist(), "reason": "outside the joint limits"})
            continue
        T_C_T = T_C_T0 @ T_T0_B @ kin.forward(q) @ T_E_T
        if not _visible(T_C_T, config.tracker):
            left_out.append({"joints_rad": q.tolist(), "reason": "target predicted out of view before the move"})
        elif not _visible(F.invert(T_C_Cn) @ T_C_T, config.tracker):
            left_out.append({"joints_rad": q.tolist(), "reason": "target predicted out of view after the move"})
        else:
            usable.append(q)
            positions.append(T_C_T[:3, 3])
    chosen_at = [T_C_T0[:3, 3]]
    chosen: list[np.ndarray] = []
    while usable and len(chosen) < count - 1:
        gap = [min(np.linalg.norm(p - c) for c in chosen_at) for p in positions]
        k = int(np.argmax(gap))
        chosen.append(usable.pop(k))
        chosen_at.append(positions.pop(k))
    return chosen, left_out



def pose_transfer(T_W_C: np.ndarray, before: list[PoseReading], after: list[PoseReading], moved: list[bool],
                  config: CellConfig, installation: Installation) -> F.PoseTransfer:
    """The new station from the pairs read at the same arm poses (old camera ``before``, new camera ``after``):
    each pair's covariance is both readings' (``uncertainty.transfer_covariance``) and, where the arm left the
    pose and came back between them (``moved``: all but the last pose read before the tracker's move, where the
    arm stood), twice one move's repeatability (``[arm] repeatability``, the target levered off the flange)."""
    single = F.coordinate_transfer(T_W_C, before[0].T_C_T, after[0].T_C_T)
    sigma_mm, sigma_rad = config.arm.repeatability.sigma()
    T_T_E = F.invert(installation.T_E_T)
    covariances = []
    for b, a, m in zip(before, after, moved, strict=True):
        C = transfer_covariance(T_W_C, b.covariance, single, a.covariance)
        if m:
            lever_W = (T_W_C @ b.T_C_T)[:3, :3] @ -T_T_E[:3, 3]
            C = C + 2.0 * arm_repeatability_covariance(sigma_mm, sigma_rad, lever_W)
        covariances.append(C)
    return F.coordinate_transfer_poses(T_W_C, [b.T_C_T for b in before], [a.T_C_T for a in after], covariances)


def reestablish(state: RunState, i: int, fresh_T_C_T: np.ndarray, mid_transfer: bool) -> tuple[RunState, dict]:
    """At a resume before step ``i``: the state with the tracker's frame re-established where the fresh reading of
    the still target (mm) disagrees with the last journaled one, and the resume's journal fields (deviation mm and
    deg, whether re-established). A tracker mid-transfer (``mid_transfer``) or a target moved since its last
    reading is not compared."""
    entry: dict = {"T_C_T": fresh_T_C_T.tolist()}
    last = state.last_still_T_C_T
    if last is None or mid_transfer:
        return state, entry
    d_mm, d_rad = F.pose_error(fresh_T_C_T, last)
    entry |= {"deviation_mm": d_mm, "deviation_deg": float(np.degrees(d_rad))}
    if d_mm <= RESUME_TOLERANCE_MM and np.degrees(d_rad) <= RESUME_TOLERANCE_DEG:
        return state, entry
    T_W_T = state.T_W_C @ last
    log.warning("resume at step %d: tracker moved while down (%.3f mm); frame re-established from the still target "
                "at %s", i, d_mm, T_W_T[:3, 3].round(3).tolist())
    return replace(state, T_W_C=F.coordinate_transfer(state.T_W_C, last, fresh_T_C_T)), entry | {"reestablished": True}


async def return_from_transfer(session: CellSession, plan: Plan, committed: set[int],
                               notes: Callable[[int], dict[str, dict]], config: CellConfig) -> bool:
    """Undo the half transfer of an abandoned (failed, cancelled) job: where its first uncommitted step is a
    ``move_tracker`` whose reading before the move was noted, drive the tracking robot back to the odometry noted
    with it (and the arm back to the transfer's own pose where it read at several), through the gate. Returns
    whether it drove; the next job then finds the tracker where it stood."""
    i = next((k for k in range(len(plan.steps)) if k not in committed), None)
    if i is None or not isinstance(plan.steps[i], MoveTracker):
        return False
    before = notes(i).get("before", {})
    odo = before.get("odometry")
    if odo is None:
        return False
    async with session.gate.motion(Robot.TRACKING) as robot:
        await robot.chassis.move_to(ChassisPose(*odo), config.tracking_chassis.timeout_s)
    q0 = before.get("poses", [{}])[0].get("joints_rad")
    if q0 is not None:  # a transfer over several arm poses: the arm back at the transfer's own pose too
        async with session.gate.motion(Robot.MEASURE) as robot:
            await robot.arm.move_joints(np.array(q0, float), config.arm.timeout_s)
    log.warning("abandoned transfer of step %d undone: the tracking robot is back at %s", i, odo)
    return True


@dataclass(frozen=True)
class TransferReadings:
    """A job's readings of the still target for a coordinate transfer over several arm poses: its cell's arm
    moved through the gate ``gate`` (one robot moves at a time) and its tracker read at rest
    (``tracker.transfer_samples`` averaged), at poses from its ``plan`` and mounts ``installation``; the readings
    before the tracker moves are noted in its ``journal``, so that a transfer interrupted by a crash, a safety stop
    or a device fault completes from them (docs/architecture.md, "Coordinate transfers")."""

    cell: Cell
    gate: MotionGate
    config: CellConfig
    installation: Installation
    plan: Plan
    journal: StepJournal

    async def at_poses(self, joints: list[np.ndarray | None], side: str, required: int | None = None
                       ) -> tuple[list[PoseReading | None], list[dict]]:
        """The still target read at each of ``joints`` in order, the arm moved there first through the gate
        (None: not commanded). The pose ``required`` is the transfer's own and must be seen
        (:class:`TargetNotVisible` otherwise, as a one-pose transfer); another found hidden is None, logged and
        listed (``side``: "before" or "after" the tracker's move)."""
        out: list[PoseReading | None] = []
        dropped: list[dict] = []
        for k, q in enumerate(joints):
            if q is not None:
                async with self.gate.motion(Robot.MEASURE) as robot:
                    await robot.arm.move_joints(q, self.config.arm.timeout_s)
            try:
                r = await read_for_transfer(self.cell.tracker, self.config.tracker)
            except TargetNotVisible as e:
                if k == required:
                    raise
                log.warning("coordinate transfer: arm pose %s left out, target hidden %s the tracker's move: %s",
                            None if q is None else np.degrees(q).round(1).tolist(), side, e.reason)
                dropped.append({"joints_rad": None if q is None else q.tolist(), "side": side, "reason": e.reason})
                out.append(None)
                continue
            out.append(PoseReading(q, r.T_C_T, r.covariance))
        return out, dropped

    async def own_or_fallback(self, q0: np.ndarray | None, fallbacks: list[np.ndarray], T_C_Cn: np.ndarray
                              ) -> tuple[PoseReading, list[dict]]:
        """The still target read at the transfer's own pose ``q0`` (where the arm stands); where it is hidden
        there, at the first of ``fallbacks`` (joints rad, :func:`fallback_joints`) within the joint limits where
        it is seen and predicted inside the view of the tracker's next station too (``T_C_Cn``,
        :func:`camera_move`). Returns the reading and the poses found unusable (joints, side, reason); raises
        :class:`TargetNotVisible` when none is."""
        try:
            first, _ = await self.at_poses([q0], "before", required=0)
            return first[0], []
        except TargetNotVisible as e:
            own = e.reason
        unusable = [{"joints_rad": None if q0 is None else q0.tolist(), "side": "before",
                     "reason": f"the transfer's own pose: {own}"}]
        kin = ArmKinematics(self.config.arm)
        T_Cn_C = F.invert(T_C_Cn)
        for q in fallbacks:
            if not kin.within_limits(q):
                unusable.append({"joints_rad": q.tolist(), "side": "before", "reason": "outside the joint limits"})
                continue
            (reading,), hidden = await self.at_poses([q], "before")
            unusable += hidden
            if reading is None:
                continue
            if not _visible(T_Cn_C @ reading.T_C_T, self.config.tracker):
                unusable.append({"joints_rad": q.tolist(), "side": "before",
                                 "reason": "target predicted out of view after the move"})
                continue
            log.warning("coordinate transfer: target hidden at the transfer's own pose (%s); read at %s instead",
                        own, np.degrees(q).round(1).tolist())
            return reading, unusable
        raise TargetNotVisible("tracker", f"{own} at the transfer's own pose, and no other of the {len(fallbacks)} "
                                          "poses at this station is seen from both tracker stations")

    async def before_move(self, step: MoveTracker, i: int) -> tuple[list[PoseReading], list[dict]]:
        """The target's readings before the tracker moves in the transfer of step ``i``, and the poses left out
        with their reason: read where the arm stands (or, where it is hidden there, at the first pose of the
        station that both tracker stations see: :meth:`own_or_fallback`), then at the poses
        :func:`choose_transfer_poses` picks for ``tracker.transfer_arm_poses``, and noted in the journal (with the
        tracking chassis' odometry) before the tracker moves; or, at a resume, the ones noted (a one-pose
        transfer's note: its reading, the arm not commanded)."""
        noted = self.journal.notes(i).get("before")
        if noted is not None:
            return [PoseReading.from_json(p) for p in noted.get("poses", [noted])], list(noted.get("left_out", []))
        plan, committed, config = self.plan, self.journal.committed, self.config
        q0, others = transfer_joints(plan, i, committed, await self.cell.arm.joints())
        odo = await self.cell.tracking_chassis.odometry()
        T_C_Cn = camera_move(self.installation, (odo.x_mm, odo.y_mm, odo.heading_rad), step)
        around = [] if q0 is None else offset_poses(q0, config, self.installation)
        first, dropped = await self.own_or_fallback(q0, fallback_joints(plan, i, committed, around, others), T_C_Cn)
        chosen = []
        if first.joints_rad is not None:
            rest = [q for q in others if not np.allclose(q, first.joints_rad)]
            chosen, left_out = choose_transfer_poses(first.joints_rad, rest, first.T_C_T, T_C_Cn,
                                                     config.tracker.transfer_arm_poses, config, self.installation)
            dropped += left_out
        rest, hidden = await self.at_poses(chosen, "before")
        before = [first, *(r for r in rest if r is not None)]
        dropped += hidden
        await self.journal.note(i, "before", {
            "T_C_T": before[0].T_C_T.tolist(), "covariance": before[0].covariance.tolist(),
            "odometry": [odo.x_mm, odo.y_mm, odo.heading_rad], "poses": [p.to_json() for p in before],
            "left_out": dropped})
        return before, dropped

    async def after_move(self, before: list[PoseReading]) -> tuple[list[PoseReading | None], list[dict]]:
        """The target read again at the poses of ``before`` once the tracker moved, in reverse order so that the
        arm ends where it stood (the transfer's own pose must be seen), returned in the order of ``before``;
        and the poses found hidden."""
        back = [p.joints_rad for p in reversed(before)]
        after, hidden = await self.at_poses(back, "after", required=len(back) - 1)
        return after[::-1], hidden
