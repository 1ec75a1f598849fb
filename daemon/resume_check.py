"""Where the robots stand when a job resumes after a restart, against where its journal left them (docs/daemon.md,
how a job survives a crash).

Each AGV's journaled pose is the odometry its last committed drive ended at (``move_measure`` for the measurement
robot, ``move_tracker`` for the tracking robot); a chassis that reports another pose beyond ``[job]
resume_pose_tolerance_mm`` / ``_deg`` was moved, or its odometry started afresh (a real chassis driver starts at
``[can] odometry_start_*`` whenever the daemon starts). The tracker is the witness of which: where it sees the target
where the journal left it, nothing moved and the odometry is re-localised; otherwise the one robot whose odometry
moved is re-localised by the tracker, and where that cannot be told the operator decides.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from tandemscan.daemon.motion import Robot
from tandemscan.drivers.interfaces import ChassisPose
from tandemscan.pipeline.planning.plan import MoveMeasure, MoveTracker, Plan

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


def as_tuple(pose: ChassisPose) -> tuple[float, float, float]:
    """``(x_mm, y_mm, heading_rad)``: a pose as the journal keeps an odometry."""
    return (pose.x_mm, pose.y_mm, pose.heading_rad)


def journaled_pose(plan: Plan, committed: Mapping[int, dict], i: int, kind: type) -> ChassisPose | None:
    """The odometry the last committed step of ``kind`` before step ``i`` ended at; None where none drove."""
    last = next((k for k in sorted(committed, reverse=True) if k < i and isinstance(plan.steps[k], kind)), None)
    return None if last is None else ChassisPose(*committed[last]["odometry"])


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
