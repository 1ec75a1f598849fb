"""Well-conditioned scanner views of the calibration plate for hand-eye data collection.

The views sit on a cone around the plate normal at the scanner's sweet-spot distance, at evenly spread
azimuths, each rolled about its own view axis by a different amount, so the relative rotations between
views turn about many different axes (what ``A X = X B`` needs to be observable).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from tandemscan.config.models import CalibrationConfig, ScannerConfig
from tandemscan.pipeline.geometry.frames import invert, make_transform
from tandemscan.pipeline.geometry.kinematics import ArmKinematics


def look_at(eye_mm: ArrayLike, target_mm: ArrayLike, roll_rad: float = 0.0) -> np.ndarray:
    """Scanner pose ``T_P_S`` (mm) at ``eye`` with its z axis through ``target`` (both in frame P).

    Scanner frame: z along the view, x right, y down. With zero roll, x is perpendicular to the plate's y
    axis (or to its x axis when looking almost along y); ``roll_rad`` turns x and y about the view axis.
    """
    eye = np.asarray(eye_mm, dtype=float)
    z = np.asarray(target_mm, dtype=float) - eye
    z /= np.linalg.norm(z)
    ref = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(ref, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll_rad), np.sin(roll_rad)
    x, y = c * x + s * y, -s * x + c * y
    return make_transform(np.column_stack([x, y, z]), eye)


def plate_view_poses(
    n: int,
    centre_P_mm: ArrayLike,
    distance_mm: float,
    tilt_deg: float,
    roll_span_deg: float = 60.0,
) -> list[np.ndarray]:
    """``n`` scanner poses ``T_P_S`` looking at ``centre_P_mm`` from ``distance_mm`` along the plate's +z side.

    The first view looks straight down the plate normal; the others are tilted by ``tilt_deg`` (alternating
    full and half tilt) at golden-angle azimuths, with rolls spread over +-``roll_span_deg / 2``.
    """
    if n < 1:
        raise ValueError("need at least one view")
    centre = np.asarray(centre_P_mm, dtype=float)
    golden = np.pi * (3.0 - np.sqrt(5.0))
    poses = []
    for i in range(n):
        tilt = 0.0 if i == 0 else np.radians(tilt_deg) * (1.0 if i % 2 else 0.5)
        az = i * golden
        v = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
        roll = np.radians(roll_span_deg) * (((i * 0.618034) % 1.0) - 0.5)
        poses.append(look_at(centre + distance_mm * v, centre, roll))
    return poses


def plate_view_distance(range_min_mm: float, range_max_mm: float, sphere_radius_mm: float) -> float:
    """Scanner-to-plate-centre distance (mm) that keeps the spheres' visible caps mid-range under tilt."""
    return 0.5 * (range_min_mm + range_max_mm) + 0.5 * sphere_radius_mm


def calibration_views(cal: CalibrationConfig, scanner: ScannerConfig) -> list[np.ndarray]:
    """The calibration job's scanner poses ``T_P_S`` over the configured plate."""
    centre = np.array([cal.centre_A_mm, cal.centre_X_mm, cal.centre_Y_mm]).mean(axis=0)
    d = plate_view_distance(scanner.range_min_mm, scanner.range_max_mm, cal.sphere_diameter_mm / 2.0)
    return plate_view_poses(cal.poses, centre, d, cal.tilt_deg, cal.roll_span_deg)


def arm_joints_for_views(
    views_T_P_S: list[np.ndarray],
    T_V2_P: np.ndarray,
    T_V2_B: np.ndarray,
    T_E_S: np.ndarray,
    kinematics: ArmKinematics,
    seed_rad: np.ndarray,
    restarts: int = 2,
) -> list[tuple[int, np.ndarray]]:
    """(view index, joints rad) for every view the arm reaches, each IK seeded by the previous solution.

    Uses the nominal mounts: a view off by their error (mm) still shows the plate.
    """
    out = []
    seed = np.asarray(seed_rad, dtype=float)
    T_B_P = invert(T_V2_B) @ T_V2_P
    for i, T_P_S in enumerate(views_T_P_S):
        q = kinematics.inverse(T_B_P @ T_P_S @ invert(T_E_S), seed, restarts=restarts)
        if q is not None:
            out.append((i, q))
            seed = q
    return out
