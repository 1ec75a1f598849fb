"""Where the robots stand when a job resumes after a restart, against where its journal left them (docs/daemon.md,
how a job survives a crash).

Each AGV's journaled pose is the odometry its last committed drive ended at (``move_measure`` for the measurement
robot, ``move_tracker`` for the tracking robot); a chassis that reports another pose beyond ``[job]
resume_pose_tolerance_mm`` / ``_deg`` was moved, or its odometry started afresh (a real chassis driver starts at
``[can] odometry_start_*`` whenever the daemon starts). The tracker is the witness of which: where it sees the target
where the journal left it, nothing moved and the odometry is re-localised; otherwise the one robot whose odometry
moved is re-localised by the tracker, and where that cannot be told the operator decides.

The arm is checked too: its joints read back against those of the last committed ``move_arm`` (a move cut short by a
stop or a crash, an arm jogged while the job was paused), beyond ``[job] resume_joint_tolerance_deg``. The target
rides on the arm, so where the arm stands elsewhere than at the last still reading the tracker's witness is the
measurement AGV's pose (Eq. 5) from each reading at the joints it was read at, not the two readings themselves.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from tandemscan.daemon.cell.motion import Robot
from tandemscan.drivers.interfaces import ChassisPose
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.kinematics import ArmKinematics, arm_base_on_column
from tandemscan.pipeline.planning.plan import MoveArm, MoveMeasure, MoveTracker, Plan, Scan
from tandemscan.pipeline.stitching.installation import Installation

#: each AGV's robot and the plan step whose committed result holds its journaled odometry
CHASSIS = {"measure_chassis": (Robot.MEASURE, MoveMeasure), "tracking_chassis": (Robot.TRACKING, MoveTracker)}


@dataclass(frozen=True)
class ChassisOff:
    """An AGV whose odometry disagrees with the journal at a resume: the journaled and reported poses (mm, rad)
    and how far apart (mm, deg)."""

    name: str
    journaled: ChassisPose
    reported: ChassisPose
    off_mm: float
    off_deg: float

    def entry(self) -> dict:
        return {"journaled": as_tuple(self.journaled), "reported": as_tuple(self.reported),
                "off_mm": round(self.off_mm, 3), "off_deg": round(self.off_deg, 4)}


@dataclass(frozen=True)
class ArmOff:
    """The arm found at a resume off the joints the journal left it at: both (rad) and the largest joint difference
    (deg)."""

    journaled: np.ndarray
    read_back: np.ndarray
    off_deg: float

    def entry(self) -> dict:
        return {"journaled_deg": np.degrees(self.journaled).round(3).tolist(),
                "read_back_deg": np.degrees(self.read_back).round(3).tolist(), "off_deg": round(self.off_deg, 3)}


@dataclass(frozen=True)
class TargetAtRest:
    """A still reading of the target in the journal: the camera in W then (``T_W_C``), the reading (``T_C_T``; mm)
    and the arm's joints it was read at (rad)."""

    T_W_C: np.ndarray
    T_C_T: np.ndarray
    joints_rad: np.ndarray


def as_tuple(pose: ChassisPose) -> tuple[float, float, float]:
    """``(x_mm, y_mm, heading_rad)``: a pose as the journal keeps an odometry."""
    return (pose.x_mm, pose.y_mm, pose.heading_rad)


def journaled_pose(plan: Plan, committed: Mapping[int, dict], i: int, kind: type) -> ChassisPose | None:
    """The odometry the last committed step of ``kind`` before step ``i`` ended at; None where none drove."""
    last = next((k for k in sorted(committed, reverse=True) if k < i and isinstance(plan.steps[k], kind)), None)
    return None if last is None else ChassisPose(*committed[last]["odometry"])


def journaled_joints(plan: Plan, committed: Mapping[int, dict], i: int) -> np.ndarray | None:
    """The joints (rad) the last committed ``move_arm`` before step ``i`` moved the arm to (re-solved where the job
    relocalises); None where no arm move was committed."""
    last = next((k for k in sorted(committed, reverse=True) if k < i and isinstance(plan.steps[k], MoveArm)), None)
    return None if last is None else np.array(committed[last]["joints_rad"], float)


def arm_off_journal(journaled: np.ndarray | None, read_back: np.ndarray, tolerance_deg: float) -> ArmOff | None:
    """The arm off its ``journaled`` joints where a joint ``read_back`` (rad) is more than ``tolerance_deg`` from
    them; None where it is not, or where the journal has no arm move."""
    if journaled is None:
        return None
    off_deg = float(np.degrees(np.max(np.abs(np.asarray(read_back, float) - journaled))))
    return ArmOff(journaled, np.asarray(read_back, float), off_deg) if off_deg > tolerance_deg else None


def last_target_at_rest(plan: Plan, committed: Mapping[int, dict], i: int) -> TargetAtRest | None:
    """The last scan's reading before step ``i`` where neither AGV nor the column moved since (arm moves may lie
    between: the joints say where the target was); None where there is none."""
    for k in sorted((k for k in committed if k < i), reverse=True):
        step, result = plan.steps[k], committed[k]
        if isinstance(step, MoveArm) or (isinstance(step, Scan) and "T_C_T" not in result):  # a scan left out
            continue
        if not isinstance(step, Scan):  # a drive, a tracker move, a column move
            return None
        return TargetAtRest(np.array(result["T_W_C"], float), np.array(result["T_C_T"], float),
                            np.array(result["joints_rad"], float))
    return None


def agv_shift(installation: Installation, kinematics: ArmKinematics, lift_mm: float, then: TargetAtRest,
              T_W_C: np.ndarray, T_C_T: np.ndarray, joints_rad: np.ndarray) -> tuple[float, float]:
    """How far (mm, deg) the measurement AGV stands, by a reading ``T_C_T`` with the camera at ``T_W_C`` and the arm
    at ``joints_rad``, from where the reading ``then`` put it (Eq. 5 for both, the column at ``lift_mm``)."""
    T_V2_B = arm_base_on_column(installation.T_V2_B, lift_mm)

    def agv(T_W_C_: np.ndarray, T_C_T_: np.ndarray, q: np.ndarray) -> np.ndarray:
        return F.measurement_agv_in_world(T_W_C_ @ T_C_T_, T_V2_B, kinematics.forward(q), installation.T_E_T)

    d_mm, d_rad = F.pose_error(agv(T_W_C, T_C_T, joints_rad), agv(then.T_W_C, then.T_C_T, then.joints_rad))
    return float(d_mm), float(np.degrees(d_rad))


def planned_scanner_pose(plan: Plan, committed: Mapping[int, dict], i: int, installation: Installation,
                         kinematics: ArmKinematics, lift_mm: float) -> np.ndarray | None:
    """``T_F_S`` (mm) the plan means scan step ``i`` to be taken from: the scanner pose of the last committed
    ``move_arm`` before it where the plan has one, else its journaled joints at the plan's AGV station before it (the
    column at ``lift_mm``); None where no arm move was committed or no drive precedes it."""
    arm = next((k for k in sorted(committed, reverse=True) if k < i and isinstance(plan.steps[k], MoveArm)), None)
    if arm is None:
        return None
    if plan.steps[arm].T_F_S is not None:
        return np.array(plan.steps[arm].T_F_S, float)
    drive = next((s for s in reversed(plan.steps[:i]) if isinstance(s, MoveMeasure)), None)
    if drive is None:
        return None
    T_V2_B = arm_base_on_column(installation.T_V2_B, lift_mm)
    return F.compose(F.planar_pose(drive.x_mm, drive.y_mm, drive.heading_rad), T_V2_B,
                     kinematics.forward(np.array(committed[arm]["joints_rad"], float)), installation.T_E_S)


def view_reaches_box(T_F_S: np.ndarray, box_min_mm: np.ndarray, box_max_mm: np.ndarray, range_min_mm: float,
                     range_max_mm: float) -> bool:
    """Whether the scanner's optical axis (+z of S at ``T_F_S``, mm) passes through the box (F, mm) within the
    working range ``range_min_mm`` .. ``range_max_mm`` (slab test)."""
    origin, axis = np.asarray(T_F_S, float)[:3, 3], np.asarray(T_F_S, float)[:3, 2]
    t0, t1 = range_min_mm, range_max_mm
    for k in range(3):
        if abs(axis[k]) < 1e-12:
            if not box_min_mm[k] <= origin[k] <= box_max_mm[k]:
                return False
            continue
        a, b = (box_min_mm[k] - origin[k]) / axis[k], (box_max_mm[k] - origin[k]) / axis[k]
        t0, t1 = max(t0, min(a, b)), min(t1, max(a, b))
    return t0 <= t1


def chassis_pose_of(T_F_V: np.ndarray) -> ChassisPose:
    """The floor pose (x, y mm; heading rad about +z) of a chassis' 4x4 pose in the plan's frame F."""
    T = np.asarray(T_F_V, float)
    return ChassisPose(float(T[0, 3]), float(T[1, 3]), float(np.arctan2(T[1, 0], T[0, 0])))


def pose_difference(a: ChassisPose, b: ChassisPose) -> tuple[float, float]:
    """Planar distance (mm) and heading difference (deg, wrapped) between two chassis poses."""
    turn = math.remainder(a.heading_rad - b.heading_rad, 2 * math.pi)
    return math.hypot(a.x_mm - b.x_mm, a.y_mm - b.y_mm), abs(math.degrees(turn))


async def chassis_off_journal(cell, plan: Plan, committed: Mapping[int, dict], i: int, mid_transfer: bool,
                              tolerance_mm: float, tolerance_deg: float) -> dict[str, ChassisOff]:
    """The AGVs whose reported odometry is off their journaled pose at a resume before step ``i`` (the tracking
    robot not checked ``mid_transfer``: it may stand anywhere on its way)."""
    off = {}
    for name, (_, kind) in CHASSIS.items():
        journaled = journaled_pose(plan, committed, i, kind)
        if journaled is None or (name == "tracking_chassis" and mid_transfer):
            continue
        reported = await getattr(cell, name).odometry()
        d_mm, d_deg = pose_difference(reported, journaled)
        if d_mm > tolerance_mm or d_deg > tolerance_deg:
            off[name] = ChassisOff(name, journaled, reported, d_mm, d_deg)
    return off


async def relocalise_odometry(gate, off: Mapping[str, ChassisOff]) -> None:
    """Each AGV of ``off`` stands where the journal left it: its odometry is set back to that pose (through its
    robot's motion capability: later drives are closed on it)."""
    for name, chassis_off in off.items():
        async with gate.motion(CHASSIS[name][0]) as robot:
            await robot.chassis.set_odometry(chassis_off.journaled)
