"""The calibration job: scan the plate from well-conditioned arm poses, read the tracker, solve ``T_T_S``.

Plan (nominal mounts): views on a cone over the plate (rotations about different axes), each turned into
joints by IK; a view the arm cannot reach, where the tracker cannot see the target, or where the plate fit
fails is skipped with a logged reason. Then ``solve_hand_eye`` (config ``calibration.method``) and a JSON
calibration file that ``measure`` reads when ``job.installation_source = "calibration"``: the four mounts
(``T_T_S`` calibrated, the others nominal, see docs/calibration.md) plus the solver's residuals.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tandemscan.config.models import CellConfig
from tandemscan.drivers.errors import TargetNotVisible
from tandemscan.pipeline import frames as F
from tandemscan.pipeline.calibration.hand_eye import HandEyeError, HandEyeResult, solve_hand_eye
from tandemscan.pipeline.calibration.plate import PlateError, fit_plate, nominal_centres_P
from tandemscan.pipeline.calibration.poses import arm_joints_for_views, plate_view_distance, plate_view_poses
from tandemscan.pipeline.installation import Installation
from tandemscan.pipeline.kinematics import ArmKinematics
from tandemscan.sim_drivers.cell import Cell

log = logging.getLogger(__name__)

#: candidate views planned per pose wanted: some are unreachable or hide the target from the tracker
_CANDIDATES_PER_POSE = 1.5


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

    def to_json(self) -> dict:
        """The calibration file's content: the four mounts and how they were obtained."""
        return {
            **self.installation.to_json(),
            "sources": {"T_T_S": f"hand-eye ({self.hand_eye.method})", "T_V1_C": "nominal", "T_V2_B": "nominal",
                        "T_E_S": "nominal"},
            "hand_eye": self.hand_eye.summary(),
            "poses_used": self.poses_used,
            "skipped": self.skipped,
            **({"sim_truth_error": self.truth_error} if self.truth_error else {}),
        }


async def run_calibration(
    cell: Cell, config: CellConfig, out_file: Path | None = None, progress: Callable[[int, int, str], None] | None = None
) -> CalibrationRun:
    """Run the calibration job on a connected cell; writes and returns the calibration."""
    cal = config.calibration
    progress = progress or (lambda done, total, msg: None)
    out_file = Path(out_file or cal.output_file)
    nominal = Installation.nominal(config.installation)
    if cell.world is not None:
        from tandemscan.sim_drivers.plate import install_calibration_plate  # sim only: the plate is physical

        install_calibration_plate(cell.world, cal)
    centre = nominal_centres_P(cal).mean(axis=0)
    distance = plate_view_distance(config.scanner.range_min_mm, config.scanner.range_max_mm,
                                   cal.sphere_diameter_mm / 2.0)
    views = plate_view_poses(int(np.ceil(cal.poses * _CANDIDATES_PER_POSE)), centre, distance, cal.tilt_deg)
    await cell.arm.enable()
    seed = await cell.arm.joints()
    kinematics = ArmKinematics(config.arm)
    progress(0, cal.poses, "planning arm poses over the plate")
    plan = await asyncio.to_thread(arm_joints_for_views, views, cal.T_V2_P.matrix(), nominal.T_V2_B,
                                   nominal.T_E_S, kinematics, seed)
    skipped = [f"view {i}: out of reach" for i in range(len(views)) if i not in {j for j, _ in plan}]
    tracker_poses, covariances, plate_poses, centre_sigma = [], [], [], []
    for i, q in plan:
        if len(tracker_poses) >= cal.poses:
            break
        progress(len(tracker_poses), cal.poses, f"view {i}: scanning the plate")
        await cell.arm.move_joints(q, config.arm.timeout_s)
        try:
            reading = await cell.tracker.read_pose(config.tracker.timeout_s)
        except TargetNotVisible as e:
            skipped.append(f"view {i}: {e}")
            continue
        frame = await cell.scanner.capture(config.scanner.timeout_s)
        try:
            fit = await asyncio.to_thread(fit_plate, frame.points_mm, cal, normals_S=frame.normals,
                                          noise_mm=config.scanner.noise_sigma_mm)
        except PlateError as e:
            skipped.append(f"view {i}: {e}")
            continue
        tracker_poses.append(reading.T_C_T)
        covariances.append(reading.covariance)
        plate_poses.append(fit.T_S_P)
        centre_sigma.append(fit.centre_sigma_mm)
    for s in skipped:
        log.info("calibration: %s", s)
    if len(tracker_poses) < 3:
        raise CalibrationJobError(f"only {len(tracker_poses)} usable plate views: {'; '.join(skipped)}")
    try:
        result = await asyncio.to_thread(
            solve_hand_eye, np.array(tracker_poses), np.array(plate_poses), cal.method,
            plate_points_P=nominal_centres_P(cal), tracker_covariances=np.array(covariances),
            plate_sigma_mm=float(np.median(centre_sigma)), min_pair_rotation_deg=cal.min_pair_rotation_deg,
        )
    except HandEyeError as e:
        raise CalibrationJobError(f"hand-eye calibration failed: {e}") from e
    installation = Installation(nominal.T_V1_C, nominal.T_V2_B, nominal.T_E_S, result.T_T_S)
    truth = None
    if cell.world is not None:
        mm, rad = F.pose_error(result.T_T_S, cell.world.truth.T_T_S)
        nmm, nrad = F.pose_error(nominal.T_T_S, cell.world.truth.T_T_S)
        truth = {"T_T_S_err_mm": mm, "T_T_S_err_deg": float(np.degrees(rad)),
                 "nominal_T_T_S_err_mm": nmm, "nominal_T_T_S_err_deg": float(np.degrees(nrad))}
    run = CalibrationRun(installation, result, out_file, len(tracker_poses), skipped, truth)
    _write_json(out_file, run.to_json())
    progress(cal.poses, cal.poses, "done")
    return run


def _write_json(path: Path, data: dict) -> None:
    """Write atomically and durably."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=1)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


__all__ = ["CalibrationJobError", "CalibrationRun", "run_calibration"]
