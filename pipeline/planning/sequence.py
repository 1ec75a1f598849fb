"""The unified command sequence: one robot moves while the other stands still (docs/planning.md).

Input: the scan poses in their measuring order (station by station, each raster ordered), the tracker chain
and its covers. While the tracker stands at chain station ``k``, the measurement robot scans every pose not
yet scanned that station ``k`` sees, starting from where it stands and going on around the part. Then it
goes to a pose that both station ``k`` and ``k + 1`` see (the last scan when it qualifies) and the tracker
moves: a ``move_tracker`` step, which the job runner executes as a coordinate transfer (Eq. 2). Before the
measurement AGV drives or its lifting column moves, the arm folds to its travel pose. Each scan's arm move
carries its planned scanner pose, so the runner can re-solve the joints where the AGV really stands. Each
transfer names the other poses at its AGV station and column height that both stations see (nearest in joints
first), where the runner reads the target when it is hidden at the transfer's own pose.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from tandemscan.pipeline.planning.plan import MoveArm, MoveLift, MoveMeasure, MoveTracker, Plan, Scan

log = logging.getLogger(__name__)


class SequenceError(ValueError):
    """The chain and the covers do not allow a sequence (a transfer with no shared measuring point)."""


@dataclass(frozen=True)
class PoseRef:
    """One scan pose as the sequencer sees it: its AGV station pose (x mm, y mm, heading rad), joints (rad),
    when known the scanner pose ``T_F_S`` (part frame, mm) those joints reach from that station, and the
    lifting column's height they assume."""

    station: int
    agv_pose: tuple[float, float, float]
    joints_rad: tuple[float, ...]
    label: str
    T_F_S: np.ndarray | None = None
    lift_mm: float | None = None  # the lifting column's height (mm) the joints assume; None: the cell has none


@dataclass(frozen=True)
class Sequence:
    """The plan, which tracker station each scan was read from, and the transfer poses (indices into poses)."""

    plan: Plan
    scan_order: tuple[int, ...]
    scan_tracker_station: tuple[int, ...]
    transfer_poses: tuple[int, ...]


class _Builder:
    def __init__(self, home_rad: np.ndarray):
        self.steps: list = []
        self.home = tuple(float(v) for v in home_rad)
        self.agv: tuple[float, float, float] | None = None
        self.joints: tuple[float, ...] | None = None
        self.lift: float | None = None

    def go(self, pose: PoseRef) -> None:
        drive = self.agv != pose.agv_pose
        lift = pose.lift_mm is not None and self.lift != pose.lift_mm
        if (drive or lift) and self.joints != self.home:  # unknown at the start: fold anyway
            self.steps.append(MoveArm(joints_rad=self.home))
            self.joints = self.home
        if drive:
            self.steps.append(MoveMeasure(x_mm=pose.agv_pose[0], y_mm=pose.agv_pose[1], heading_rad=pose.agv_pose[2]))
            self.agv = pose.agv_pose
        if lift:
            self.steps.append(MoveLift(height_mm=pose.lift_mm))
            self.lift = pose.lift_mm
        if self.joints != pose.joints_rad:
            T = None if pose.T_F_S is None else tuple(tuple(float(v) for v in row) for row in pose.T_F_S)
            self.steps.append(MoveArm(joints_rad=pose.joints_rad, T_F_S=T))
            self.joints = pose.joints_rad


def _alternatives(poses: list[PoseRef], t: int, shared: np.ndarray) -> tuple[str, ...]:
    """Labels of the ``shared`` poses (seen from both tracker stations) at pose ``t``'s AGV station and column
    height, other than ``t``, nearest to it in joints first (the largest joint change, rad)."""
    own = poses[t]
    same = [j for j in shared if j != t and poses[j].agv_pose == own.agv_pose and poses[j].lift_mm == own.lift_mm]
    turn = [float(np.max(np.abs(np.subtract(poses[j].joints_rad, own.joints_rad)))) for j in same]
    return tuple(poses[same[k]].label for k in np.argsort(turn, kind="stable"))


def build_sequence(
    poses: list[PoseRef],
    chain_poses: list[tuple[float, float, float]],
    chain_cover: np.ndarray,
    home_rad: np.ndarray,
    name: str,
    part: str = "",
    tracker_starts_at_first: bool = True,
) -> Sequence:
    """The step list for ``poses`` (in measuring order) under the tracker chain.

    ``chain_cover[k, i]``: chain station ``k`` sees pose ``i``. Poses no station sees are left out (the caller
    reports them). With ``tracker_starts_at_first`` the tracker already stands at chain station 0; otherwise
    the plan first moves it there (a transfer at the measurement robot's start pose).
    """
    cover = np.asarray(chain_cover, bool)
    if cover.shape != (len(chain_poses), len(poses)):
        raise SequenceError(
            f"cover shape {cover.shape} does not match {len(chain_poses)} stations x {len(poses)} poses")
    b = _Builder(home_rad)
    todo = cover.any(axis=0)
    order, station_of, transfers = [], [], []
    cursor = 0
    if not tracker_starts_at_first:
        x, y, h = chain_poses[0]
        b.steps.append(MoveTracker(x_mm=x, y_mm=y, heading_rad=h))
    for k in range(len(chain_poses)):
        n = len(poses)
        for i in [(cursor + j) % n for j in range(n)]:
            if todo[i] and cover[k, i]:
                b.go(poses[i])
                b.steps.append(Scan(label=poses[i].label))
                order.append(i)
                station_of.append(k)
                todo[i] = False
                cursor = i
        if k + 1 == len(chain_poses):
            break
        shared = np.flatnonzero(cover[k] & cover[k + 1])
        if len(shared) == 0:
            raise SequenceError(f"tracker stations {k} and {k + 1} share no measuring point")
        if cursor in shared:
            t = cursor
        else:  # the shared pose nearest in measuring order from where the robot stands
            t = int(shared[np.argmin((shared - cursor) % len(poses))])
        b.go(poses[t])
        x, y, h = chain_poses[k + 1]
        b.steps.append(MoveTracker(x_mm=x, y_mm=y, heading_rad=h, alternatives=_alternatives(poses, t, shared)))
        transfers.append(t)
        cursor = t
    if b.joints is not None and b.joints != b.home:
        b.steps.append(MoveArm(joints_rad=b.home))
    return Sequence(Plan(name=name, part=part, steps=b.steps), tuple(order), tuple(station_of), tuple(transfers))
