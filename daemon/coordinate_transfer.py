"""Where the tracker camera stands in the job's world frame W: the coordinate transfer (Eq. 2), its check at a
resume, and undoing a half transfer of an abandoned job.

A transfer reads the still target before and after the tracker moves; ``T_W_C`` (mm) follows from the two
readings (:func:`tandemscan.pipeline.geometry.frames.coordinate_transfer`). At a resume a fresh reading of the
still target must agree with the last journaled one; where it does not, the tracker was moved while the daemon
was down and its frame is re-established the same way. Frames: W the job's world frame, C the tracker camera,
T the target (``docs/architecture.md``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from tandemscan.config.models import CellConfig
from tandemscan.daemon.job_records import Odometry, TransferRecord
from tandemscan.daemon.run_state import RunState
from tandemscan.daemon.session import CellSession
from tandemscan.daemon.supervisor import TRACKING_ROBOT
from tandemscan.drivers.interfaces import ChassisPose, TrackerReading
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.uncertainty import transfer_covariance
from tandemscan.pipeline.planning.plan import MoveTracker, Plan

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
