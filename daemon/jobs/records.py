"""What a job's steps produce, as frozen records with their journal form (``to_json`` / ``from_json``).

One record per committed step (``docs/daemon.md``, how a job survives a crash): a scan (:class:`ScanRecord`) or a
scan left out because the tracker could not see the target (:class:`UntrackedScan`); a coordinate transfer
(:class:`TransferRecord`, Eq. 2) or a tracker relocation before the first scan (:class:`TrackerRelocation`); a
drive of the measurement AGV (:class:`MeasureMove`), an arm move (:class:`ArmMove`), a lift move
(:class:`LiftMove`). The anchor of W in the plan's frame F is journaled as a note of its step
(:class:`AnchorEntry`); a step of the AGV relocalisation carries :class:`RelocalisationEntry`. How a record
changes the job's state is :func:`tandemscan.daemon.jobs.run_state.apply`.

The JSON layout is the journal's since the daemon first resumed jobs: ``from_json`` reads what ``to_json`` writes
and what earlier versions wrote. Frames and units: ``T_a_b`` maps frame-b coordinates into frame a (mm); W the
job's world frame, C the tracker camera, T the target, S the scanner, F the plan's frame, V2 the measurement AGV;
joints in radians; odometry ``(x_mm, y_mm, heading_rad)`` in the chassis' odometry frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tandemscan.drivers.interfaces import TrackerReading
from tandemscan.pipeline.planning.plan import MoveArm, MoveLift, MoveMeasure, MoveTracker, Scan

Odometry = tuple[float, float, float]


def _matrix(value: list | None) -> np.ndarray | None:
    return None if value is None else np.array(value, dtype=float)


def _list(value: np.ndarray | None) -> list | None:
    return None if value is None else np.asarray(value).tolist()


def _odometry(value: list) -> Odometry:
    x, y, heading = value
    return (x, y, heading)


@dataclass(frozen=True)
class ScanRecord:
    """One measured pose: the raw scan's file, the tracker reading it was placed by (``T_C_T``, mm), the arm's
    joints (rad), the camera in W at the time (``T_W_C``) and the scanner in W (``T_W_S``, mm)."""

    index: int
    tracker_station: int
    file: Path
    reading: TrackerReading
    joints_rad: np.ndarray
    T_W_C: np.ndarray
    T_W_S: np.ndarray
    point_count: int

    def to_json(self) -> dict:
        """Everything but the points (in the file, named relative to the job's ``scans/`` folder)."""
        r = self.reading
        return {
            "index": self.index, "station": self.tracker_station, "file": self.file.name, "points": self.point_count,
            "T_C_T": r.T_C_T.tolist(), "covariance": r.covariance.tolist(), "timestamp_s": r.timestamp_s,
            "frame_number": r.frame_number, "joints_rad": np.asarray(self.joints_rad).tolist(),
            "T_W_C": self.T_W_C.tolist(), "T_W_S": self.T_W_S.tolist(),
        }

    @classmethod
    def from_json(cls, d: dict, job_dir: Path) -> ScanRecord:
        """Inverse of :meth:`to_json` for the job in ``job_dir``."""
        reading = TrackerReading(np.array(d["T_C_T"], dtype=float), np.array(d["covariance"], dtype=float),
                                 d["timestamp_s"], d["frame_number"])
        return cls(d["index"], d["station"], job_dir / "scans" / d["file"], reading,
                   np.array(d["joints_rad"], dtype=float), np.array(d["T_W_C"], dtype=float),
                   np.array(d["T_W_S"], dtype=float), d["points"])


@dataclass(frozen=True)
class UntrackedScan:
    """A scan left out because the tracker could not see the target: its step, the plan's label and why."""

    step: int
    label: str
    reason: str

    def entry(self) -> dict:
        """The report's entry (``relocalisation.untracked``)."""
        return {"step": self.step, "label": self.label, "reason": self.reason}

    def to_json(self) -> dict:
        return {"untracked": self.entry()}

    @classmethod
    def from_json(cls, d: dict) -> UntrackedScan:
        e = d["untracked"]
        return cls(e["step"], e["label"], e["reason"])


@dataclass(frozen=True)
class TransferRecord:
    """A coordinate transfer (Eq. 2): the tracker's new station and camera pose ``T_W_C`` (mm), the still target
    read before (``before_T_C_T``) and after (``after_T_C_T``) the move, the tracking chassis' odometry there, and
    the pose graph's error prior: the target's origin in W (``target_W_mm``) and the 6x6 covariance of both
    readings (translation mm^2 then rotation rad^2), with the number of scans before the transfer.

    A transfer over several arm poses (``[tracker] transfer_arm_poses``), or one whose own pose hid the target,
    lists the pairs it used (``arm_poses``: joints rad, ``before`` and ``after`` ``T_C_T`` mm; the first the
    transfer's own pose, or where it read instead, whose readings are ``before_T_C_T`` and ``after_T_C_T``), how
    many it asked for and the poses left out (joints, why); its prior is then the estimate's: the targets'
    centroid in W and the 6x6 covariance about it. A record journaled before these existed reads as a one-pose
    transfer."""

    station: int
    after_scan: int
    target_W_mm: np.ndarray
    covariance: np.ndarray
    T_W_C: np.ndarray
    before_T_C_T: np.ndarray
    after_T_C_T: np.ndarray
    odometry: Odometry
    arm_poses: tuple[dict, ...] = ()
    arm_poses_requested: int = 1
    arm_poses_dropped: tuple[dict, ...] = ()

    def entry(self) -> dict:
        """The transfer's entry in the report's ``transfer_log`` and the correction's prior (JSON lists)."""
        entry = {"station": self.station, "after_scan": self.after_scan, "target_W_mm": self.target_W_mm.tolist(),
                 "covariance": self.covariance.tolist()}
        if self.arm_poses_requested > 1 or self.arm_poses_dropped:  # several poses, or the own one hidden
            entry |= {"arm_poses": len(self.arm_poses), "arm_poses_requested": self.arm_poses_requested,
                      "arm_poses_left_out": list(self.arm_poses_dropped)}
        return entry

    def to_json(self) -> dict:
        out = {"T_W_C": self.T_W_C.tolist(), "station": self.station, "transfer": self.entry(),
               "before": self.before_T_C_T.tolist(), "after": self.after_T_C_T.tolist(),
               "odometry": list(self.odometry)}
        if self.arm_poses:
            out["arm_poses"] = list(self.arm_poses)
        return out

    @classmethod
    def from_json(cls, d: dict) -> TransferRecord:
        t = d["transfer"]
        return cls(t["station"], t["after_scan"], np.array(t["target_W_mm"], dtype=float),
                   np.array(t["covariance"], dtype=float), np.array(d["T_W_C"], dtype=float),
                   np.array(d["before"], dtype=float), np.array(d["after"], dtype=float), _odometry(d["odometry"]),
                   tuple(d.get("arm_poses", ())), t.get("arm_poses_requested", 1),
                   tuple(t.get("arm_poses_left_out", ())))


@dataclass(frozen=True)
class AnchorEntry:
    """W placed in the plan's frame F (Eq. 5) at ``step``, or not (``placed`` False and ``reason``): ``T_F_W``, the
    measurement AGV in F (``T_F_V2``, mm) and where the plan (or its odometry) puts it (``planned_T_F_V2``)."""

    step: int
    placed: bool
    source: str | None = None
    reason: str | None = None
    T_F_W: np.ndarray | None = None
    T_F_V2: np.ndarray | None = None
    planned_T_F_V2: np.ndarray | None = None

    def report(self) -> dict:
        """The report's ``relocalisation.anchor``."""
        if self.placed:
            return {"step": self.step, "placed": True, "source": self.source}
        return {"step": self.step, "placed": False, "reason": self.reason}

    def to_json(self) -> dict:
        """The journal's note of a placed anchor."""
        return self.report() | {"T_F_W": _list(self.T_F_W), "T_F_V2": _list(self.T_F_V2)}

    @classmethod
    def from_json(cls, d: dict, planned_T_F_V2: np.ndarray | None = None) -> AnchorEntry:
        """A noted anchor; ``planned_T_F_V2`` where the AGV was planned then (default: ``T_F_V2``, as at the
        job's start, where the AGV had not been measured before)."""
        T_F_V2 = _matrix(d.get("T_F_V2"))
        return cls(d["step"], d["placed"], d.get("source"), d.get("reason"), _matrix(d.get("T_F_W")), T_F_V2,
                   T_F_V2 if planned_T_F_V2 is None else planned_T_F_V2)


@dataclass(frozen=True)
class RelocalisationEntry:
    """A step's AGV relocalisation: the state after it (``T_F_W``, ``T_F_V2``, ``planned_T_F_V2`` in mm, None where
    unknown; the report's anchor entry) and the report entries it adds (a located station, a scan pose not
    re-solved, a nearby view scanned instead), each None where the step has none."""

    T_F_W: np.ndarray | None
    T_F_V2: np.ndarray | None
    planned_T_F_V2: np.ndarray | None
    anchor: dict | None
    located: dict | None = None
    unresolved: dict | None = None
    adjusted: dict | None = None

    def to_json(self) -> dict:
        return {"T_F_W": _list(self.T_F_W), "T_F_V2": _list(self.T_F_V2),
                "planned_T_F_V2": _list(self.planned_T_F_V2), "anchor": self.anchor, "located": self.located,
                "unresolved": self.unresolved, "adjusted": self.adjusted}

    @classmethod
    def from_json(cls, d: dict) -> RelocalisationEntry:
        return cls(_matrix(d["T_F_W"]), _matrix(d["T_F_V2"]), _matrix(d["planned_T_F_V2"]), d["anchor"],
                   d.get("located"), d.get("unresolved"), d.get("adjusted"))


def _with_relocalisation(result: dict, entry: RelocalisationEntry | None) -> dict:
    return result if entry is None else result | {"relocalisation": entry.to_json()}


def _relocalisation(d: dict) -> RelocalisationEntry | None:
    state = d.get("relocalisation")
    return None if state is None else RelocalisationEntry.from_json(state)


@dataclass(frozen=True)
class TrackerRelocation:
    """A tracker move before the first scan: W becomes the camera frame where it now stands (no transfer); the
    anchor placed from there where the job relocalises."""

    odometry: Odometry
    relocalisation: RelocalisationEntry | None = None

    def to_json(self) -> dict:
        return _with_relocalisation({"relocation": True, "odometry": list(self.odometry)}, self.relocalisation)

    @classmethod
    def from_json(cls, d: dict) -> TrackerRelocation:
        return cls(_odometry(d["odometry"]), _relocalisation(d))


@dataclass(frozen=True)
class MeasureMove:
    """A drive of the measurement AGV: its odometry at the end, and where it was located after (relocalising)."""

    odometry: Odometry
    relocalisation: RelocalisationEntry | None = None

    def to_json(self) -> dict:
        return _with_relocalisation({"odometry": list(self.odometry)}, self.relocalisation)

    @classmethod
    def from_json(cls, d: dict) -> MeasureMove:
        return cls(_odometry(d["odometry"]), _relocalisation(d))


@dataclass(frozen=True)
class ArmMove:
    """An arm move to ``joints_rad`` (the plan's, or re-solved for its scanner pose where the AGV stands)."""

    joints_rad: np.ndarray
    relocalisation: RelocalisationEntry | None = None

    def to_json(self) -> dict:
        return _with_relocalisation({"joints_rad": np.asarray(self.joints_rad).tolist()}, self.relocalisation)

    @classmethod
    def from_json(cls, d: dict) -> ArmMove:
        return cls(np.array(d["joints_rad"], dtype=float), _relocalisation(d))


@dataclass(frozen=True)
class LiftMove:
    """A lifting-column move: the height reached (mm above the arm's mount)."""

    height_mm: float

    def to_json(self) -> dict:
        return {"height_mm": self.height_mm}

    @classmethod
    def from_json(cls, d: dict) -> LiftMove:
        return cls(d["height_mm"])


StepRecord = ScanRecord | UntrackedScan | TransferRecord | TrackerRelocation | MeasureMove | ArmMove | LiftMove


def record_from_json(step: MoveTracker | MoveMeasure | MoveLift | MoveArm | Scan, result: dict,
                     job_dir: Path) -> StepRecord:
    """The record a committed ``step`` of the job in ``job_dir`` left in the journal (``result``)."""
    if isinstance(step, MoveTracker):
        return TrackerRelocation.from_json(result) if result.get("relocation") else TransferRecord.from_json(result)
    if isinstance(step, MoveMeasure):
        return MeasureMove.from_json(result)
    if isinstance(step, MoveLift):
        return LiftMove.from_json(result)
    if isinstance(step, MoveArm):
        return ArmMove.from_json(result)
    if "untracked" in result:
        return UntrackedScan.from_json(result)
    return ScanRecord.from_json(result, job_dir)
