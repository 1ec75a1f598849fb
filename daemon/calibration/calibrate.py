"""The calibration job: scan the plate from well-conditioned arm poses, read the tracker, solve ``T_T_S``.

Plan (nominal mounts): views on a cone over the plate (rotations about different axes), each turned into
joints by IK; a view the arm cannot reach, where the tracker cannot see the target, or where the plate fit
fails is skipped with a logged reason. Then ``solve_hand_eye`` (config ``calibration.method``) and a JSON
calibration file that ``measure`` reads when ``job.installation_source = "calibration"``: the four mounts
(``T_T_S`` calibrated, the others nominal, see docs/calibration.md) plus the solver's residuals. Every motion
goes through the open cell session's gate (supervisor: latch, interlock, 50 Hz safety polling); on the
simulated cell the session's calibration observer sets up the plate and scores the mounts against the truth.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from tandemscan.config.models import CalibrationConfig, CellConfig
from tandemscan.daemon.calibration.current import cell_fingerprint
from tandemscan.daemon.cell.devices import Cell
from tandemscan.daemon.cell.motion import Robot
from tandemscan.daemon.cell.session import CellSession, MotionGate
from tandemscan.daemon.cell.tracker_reading import read_at_rest
from tandemscan.drivers.errors import TargetNotVisible
from tandemscan.drivers.interfaces import ChassisPose, ChassisReadings
from tandemscan.pipeline.calibration.hand_eye import HandEyeError, HandEyeResult, solve_hand_eye
from tandemscan.pipeline.calibration.mounts import (
    MountError,
    arm_base_motions,
    mount_from_turns,
    relative_motions,
    solve_flange_mount,
)
from tandemscan.pipeline.calibration.plate import PlateError, PlateFit, fit_plate, nominal_centres_P, plate_frame
from tandemscan.pipeline.calibration.poses import arm_joints_for_views, plate_view_distance, plate_view_poses
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.kinematics import ArmKinematics
from tandemscan.pipeline.io.durable import write_durably
from tandemscan.pipeline.stitching.installation import Installation

log = logging.getLogger(__name__)

#: candidate views planned per pose wanted: some are unreachable or hide the target from the tracker
_CANDIDATES_PER_POSE = 1.5
#: chassis turns in place (deg, relative to the start heading) for the mount calibrations
_TURNS_DEG = (-8.0, -4.0, 4.0, 8.0)


class CalibrationJobError(Exception):
    """The calibration job could not produce a calibration; the message says why."""


@dataclass
class CalibrationRun:
    """What a calibration job found (mm, deg)."""

    installation: Installation
    hand_eye: HandEyeResult
    file: Path
    poses_used: int
    skipped: list[str] = field(default_factory=list)
    truth_error: dict[str, float] | None = None
    sources: dict[str, str] = field(default_factory=dict)
    made_for: str = ""  # the cell configuration's fingerprint (``calibration_state.cell_fingerprint``)
    created_utc: str = ""

    def to_json(self) -> dict:
        """The calibration file's content: the four mounts and how they were obtained, when and for which cell
        configuration (docs/calibration.md, "The current calibration")."""
        return {
            **replace(self.installation, T_T_S_covariance=self.hand_eye.covariance).to_json(),
            "created_utc": self.created_utc, "made_for": self.made_for,
            "sources": self.sources,
            "hand_eye": self.hand_eye.summary(),
            "poses_used": self.poses_used,
            "skipped": self.skipped,
            **({"sim_truth_error": self.truth_error} if self.truth_error else {}),
        }


@dataclass
class PlateViews:
    """What the plate views measured, one entry per usable view: the averaged tracker reading ``T_C_T`` (mm)
    and its covariance (driver order), the mean sphere centres in S (mm, (3, 3)) with their covariances, the
    plate pose ``T_S_P`` from them (Eq. 7-8) and the arm joints (rad)."""

    target_poses: list[np.ndarray] = field(default_factory=list)
    covariances: list[np.ndarray] = field(default_factory=list)
    plate_poses: list[np.ndarray] = field(default_factory=list)
    centres: list[np.ndarray] = field(default_factory=list)
    centre_covariances: list[np.ndarray] = field(default_factory=list)
    joints: list[np.ndarray] = field(default_factory=list)
    fits: list[list[PlateFit]] = field(default_factory=list)  # each view's plate fits (its spheres' fits)

    def add(self, T_C_T: np.ndarray, cov: np.ndarray, fits: list[PlateFit], q: np.ndarray) -> None:
        """One view: the arm stands still, so the scans' centres are averaged and their covariance shrinks
        with the count."""
        self.target_poses.append(T_C_T)
        self.covariances.append(cov)
        self.joints.append(q)
        self.fits.append(list(fits))
        self.centres.append(np.mean([f.centres_S for f in fits], axis=0))
        self.centre_covariances.append(np.mean([f.centre_covariances for f in fits], axis=0) / len(fits))
        self.plate_poses.append(plate_frame(*self.centres[-1]))


async def run_calibration(
    session: CellSession,
    config: CellConfig,
    out_file: Path | None = None,
    progress: Callable[[int, int, str], None] | None = None,
) -> CalibrationRun:
    """Run the calibration job on the cell of an open session; writes and returns the calibration."""
    cal = config.calibration
    progress = progress or (lambda done, total, msg: None)
    out_file = Path(out_file or cal.output_file)
    nominal = Installation.nominal(config.installation)
    observer = session.calibration_observer()
    if observer is not None:  # off the event loop: the supervisor's 50 Hz safety polling runs on it
        await asyncio.to_thread(observer.calibration_started)
    kinematics = ArmKinematics(config.arm)
    views, skipped = await scan_plate_views(session, config, nominal, kinematics, progress)
    result = await _solve_scanner_mount(views, cal)
    sources = {"T_T_S": f"hand-eye ({result.method}, {len(views.target_poses)} poses)"}
    T_E_S = _flange_mount(views, kinematics, result, nominal.T_E_S, sources, skipped)
    mounts, chassis_sources, chassis_skipped = await _chassis_mounts(session, config, kinematics,
                                                                     (T_E_S, result.T_T_S), nominal, progress)
    sources |= chassis_sources
    skipped += chassis_skipped
    for k in ("T_V1_C", "T_V2_B", "T_E_S"):
        sources.setdefault(k, "nominal")
    installation = Installation(mounts["T_V1_C"], mounts["T_V2_B"], T_E_S, result.T_T_S)
    truth = observer.calibration_scored(nominal, installation) if observer is not None else None
    run = CalibrationRun(installation, result, out_file, len(views.target_poses), skipped, truth, sources,
                         cell_fingerprint(config), datetime.now(UTC).isoformat(timespec="seconds"))
    _write_json(out_file, run.to_json())
    progress(cal.poses, cal.poses, "done")
    return run


async def scan_plate_views(session: CellSession, config: CellConfig, nominal: Installation,
                            kinematics: ArmKinematics, progress: Callable[[int, int, str], None],
                            ) -> tuple[PlateViews, list[str]]:
    """Plan the views over the plate (IK with the nominal mounts), then at each until ``calibration.poses``
    are usable: arm move, tracker readings at rest, plate scans. Returns the views and the skipped ones' reasons;
    :class:`CalibrationJobError` below three usable views."""
    cal, cell, gate = config.calibration, session.cell, session.gate
    centre = nominal_centres_P(cal).mean(axis=0)
    distance = plate_view_distance(config.scanner.range_min_mm, config.scanner.range_max_mm,
                                   cal.sphere_diameter_mm / 2.0)
    candidates = plate_view_poses(int(np.ceil(cal.poses * _CANDIDATES_PER_POSE)), centre, distance, cal.tilt_deg,
                                  cal.roll_span_deg)
    async with gate.motion(Robot.MEASURE) as robot:
        await robot.arm.enable()
    seed = await cell.arm.joints()
    progress(0, cal.poses, "planning arm poses over the plate")
    plan = await asyncio.to_thread(arm_joints_for_views, candidates, cal.T_V2_P.matrix(), nominal.T_V2_B,
                                   nominal.T_E_S, kinematics, seed)
    skipped = [f"view {i}: out of reach" for i in range(len(candidates)) if i not in {j for j, _ in plan}]
    views = PlateViews()
    for i, q in plan:
        if len(views.target_poses) >= cal.poses:
            break
        progress(len(views.target_poses), cal.poses, f"view {i}: scanning the plate")
        async with gate.motion(Robot.MEASURE) as robot:
            await robot.arm.move_joints(q, config.arm.timeout_s)
        try:
            T_C_T, cov = await _read_at_rest(cell, config)
            fits = [await _scan_plate(cell, config) for _ in range(cal.scans_per_pose)]
        except (TargetNotVisible, PlateError) as e:
            skipped.append(f"view {i}: {e}")
            continue
        views.add(T_C_T, cov, fits, q)
    for s in skipped:
        log.info("calibration: %s", s)
    if len(views.target_poses) < 3:
        raise CalibrationJobError(f"only {len(views.target_poses)} usable plate views: {'; '.join(skipped)}")
    return views, skipped


async def _solve_scanner_mount(views: PlateViews, cal: CalibrationConfig) -> HandEyeResult:
    """``T_T_S`` by ``solve_hand_eye`` (``calibration.method``) with the measured sphere centres and their fit
    covariances as plate points and the averaged readings' covariances (docs/calibration.md)."""
    try:
        return await asyncio.to_thread(
            solve_hand_eye, np.array(views.target_poses), np.array(views.plate_poses), cal.method,
            plate_points_P=nominal_centres_P(cal), plate_points_S=np.array(views.centres),
            tracker_covariances=np.array(views.covariances),
            plate_point_covariances=np.array(views.centre_covariances),
            min_pair_rotation_deg=cal.min_pair_rotation_deg,
        )
    except HandEyeError as e:
        raise CalibrationJobError(f"hand-eye calibration failed: {e}") from e


def _flange_mount(views: PlateViews, kinematics: ArmKinematics, hand_eye: HandEyeResult, nominal_T_E_S: np.ndarray,
                  sources: dict[str, str], skipped: list[str]) -> np.ndarray:
    """``T_E_S`` from the arm's forward kinematics and the tracker readings (``solve_flange_mount``); the
    nominal one, with the reason in ``skipped``, where that fails."""
    try:
        flange = solve_flange_mount([kinematics.forward(q) for q in views.joints], views.target_poses,
                                    hand_eye.T_T_S)
    except HandEyeError as e:
        skipped.append(f"T_E_S stays nominal: {e}")
        return nominal_T_E_S
    sources["T_E_S"] = f"arm hand-eye (park), point RMS {flange.point_rms_mm:.3f} mm"
    return flange.T_T_S


async def _chassis_mounts(session: CellSession, config: CellConfig, kinematics: ArmKinematics,
                          arm_mounts: tuple[np.ndarray, np.ndarray], nominal: Installation,
                          progress: Callable[[int, int, str], None]
                          ) -> tuple[dict[str, np.ndarray], dict[str, str], list[str]]:
    """``T_V1_C`` and ``T_V2_B`` from turns in place of each chassis in turn, the arm standing still
    (``mount_from_turns``; ``arm_mounts``: ``T_E_S`` and ``T_T_S``); a mount stays nominal where the turns
    fail. Returns the mounts, the source of each one calibrated and what was skipped, with why."""
    cal, cell = config.calibration, session.cell
    T_E_S, T_T_S = arm_mounts
    T_B_T = kinematics.forward(await cell.arm.joints()) @ T_E_S @ F.invert(T_T_S)
    mounts = {"T_V1_C": nominal.T_V1_C, "T_V2_B": nominal.T_V2_B}
    sources: dict[str, str] = {}
    skipped: list[str] = []
    for name, chassis, robot, motions_of in (
        ("T_V1_C", cell.tracking_chassis, Robot.TRACKING, lambda turns: relative_motions(F.invert(turns))),
        ("T_V2_B", cell.measure_chassis, Robot.MEASURE, lambda turns: arm_base_motions(turns, T_B_T)),
    ):
        progress(cal.poses, cal.poses, f"{name}: turning its chassis in place")
        turns = await _turn_readings(session, chassis, robot, config, skipped)
        try:
            if turns is None:
                raise MountError("the target was not visible at two headings")
            mounts[name], axis = mount_from_turns(motions_of(turns), mounts[name])
            sources[name] = f"turns in place: roll, pitch, axis distance (axis RMS {axis.line_rms_mm:.3f} mm)"
        except MountError as e:
            skipped.append(f"{name} stays nominal: {e}")
    return mounts, sources, skipped


async def _read_at_rest(cell: Cell, config: CellConfig) -> tuple[np.ndarray, np.ndarray]:
    """Mean ``T_C_T`` of ``calibration.tracker_samples`` readings at rest and its covariance (driver order)."""
    reading = await read_at_rest(cell.tracker, config.calibration.tracker_samples, config.tracker)
    return reading.T_C_T, reading.covariance


async def _turn_readings(session: CellSession, chassis: ChassisReadings, robot: Robot, config: CellConfig,
                         skipped: list[str]) -> np.ndarray | None:
    """Tracker readings with ``chassis`` (of ``robot``) turned in place by each of ``_TURNS_DEG`` (then back);
    None if the target was lost at fewer than two headings."""
    start = await chassis.odometry()
    readings = []
    for d in (0.0, *_TURNS_DEG):
        turned = ChassisPose(start.x_mm, start.y_mm, start.heading_rad + np.radians(d))
        await _drive(session.gate, robot, turned, config.measure_chassis.timeout_s)
        try:
            readings.append((await _read_at_rest(session.cell, config))[0])
        except TargetNotVisible as e:
            skipped.append(f"turn {d:+.0f} deg: {e}")
    await _drive(session.gate, robot, start, config.measure_chassis.timeout_s)
    return np.array(readings) if len(readings) >= 2 else None


async def _drive(gate: MotionGate, robot: Robot, pose: ChassisPose, timeout_s: float) -> None:
    """One move of ``robot``'s chassis through the gate."""
    async with gate.motion(robot) as handle:
        await handle.chassis.move_to(pose, timeout_s)


async def _scan_plate(cell: Cell, config: CellConfig) -> PlateFit:
    """One plate scan and its sphere fit (raises :class:`PlateError`)."""
    frame = await cell.scanner.capture(config.scanner.timeout_s)
    return await asyncio.to_thread(fit_plate, frame.points_mm, config.calibration, normals_S=frame.normals,
                                   noise_mm=config.scanner.noise_sigma_mm)


def _write_json(path: Path, data: dict) -> None:
    """Write ``data`` as JSON atomically and durably."""
    write_durably(path, lambda f: f.write(json.dumps(data, indent=1).encode("utf-8")))


__all__ = ["CalibrationJobError", "CalibrationRun", "run_calibration"]
