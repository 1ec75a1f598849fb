"""Mount calibration from turns in place: roll, pitch and distance from the chassis axis are measured; the
rotation about that axis and the height stay nominal."""

from __future__ import annotations

import numpy as np
import pytest
from tandemscan.pipeline.calibration.mounts import MountError, mount_from_turns, relative_motions, turn_axis
from tandemscan.pipeline.geometry.frames import from_rotvec, from_rpy, invert, planar_pose

T_V_C_NOMINAL = from_rpy([0.0, 0.0, 1900.0], np.radians([-100.0, 0.0, -90.0]))
T_V_C_TRUE = T_V_C_NOMINAL @ from_rotvec([2.1, -1.7, 1.2], np.radians([0.3, -0.25, 0.2]))
T_F_V = planar_pose(-1400.0, 4600.0, np.radians(-90.0))
T_F_T = from_rpy([-1500.0, 2300.0, 900.0], np.radians([180.0, 0.0, 30.0]))


SIGMA = (0.025, float(np.radians(0.0025)))  # tracker 1-sigma (mm, rad)


def _readings(turns_deg, rng=None, sigma=SIGMA):
    """``T_C_T`` while the tracking chassis turns in place and the target stands still."""
    out = []
    for th in np.radians(turns_deg):
        T_C_T = invert(T_F_V @ planar_pose(0, 0, th) @ T_V_C_TRUE) @ T_F_T
        if rng is not None:
            T_C_T = from_rotvec(rng.normal(0, sigma[0], 3), rng.normal(0, sigma[1], 3)) @ T_C_T
        out.append(T_C_T)
    return np.array(out)


def _check(T, tol_mm, tol_deg):
    z_true = T_V_C_TRUE[2, :3]  # chassis z seen from C: roll and pitch
    assert np.degrees(np.arccos(np.clip(T[2, :3] @ z_true, -1, 1))) < tol_deg
    # the result is the truth turned about the chassis axis by the (unobservable) yaw error
    D = T[:3, :3] @ T_V_C_TRUE[:3, :3].T
    yaw = np.arctan2(D[1, 0], D[0, 0])
    np.testing.assert_allclose(D, planar_pose(0, 0, yaw)[:3, :3], atol=np.radians(tol_deg))
    np.testing.assert_allclose(T[:2, 3], planar_pose(0, 0, yaw)[:2, :2] @ T_V_C_TRUE[:2, 3], atol=tol_mm)
    assert T[2, 3] == T_V_C_NOMINAL[2, 3]  # height: unobservable from turns


def test_exact_turns_recover_roll_pitch_x_y():
    motions = relative_motions(invert(_readings([0, -12, -6, 6, 12])))
    T, axis = mount_from_turns(motions, T_V_C_NOMINAL)
    _check(T, 1e-6, 1e-6)
    assert axis.line_rms_mm < 1e-9 and axis.axis_rms_rad < 1e-9
    # the nominal was millimetres off in position and tenths of a degree in tilt
    assert np.linalg.norm(T_V_C_NOMINAL[:2, 3] - T_V_C_TRUE[:2, 3]) > 2.0
    assert np.degrees(np.arccos(T_V_C_NOMINAL[2, :3] @ T_V_C_TRUE[2, :3])) > 0.2


def test_noisy_turns_are_within_tracker_noise_scale():
    rng = np.random.default_rng(4)
    motions = relative_motions(invert(_readings([0, -15, -10, -5, 5, 10, 15], rng)))
    T, _ = mount_from_turns(motions, T_V_C_NOMINAL)
    _check(T, 0.5, 0.02)


def test_too_small_turns_are_rejected():
    with pytest.raises(MountError, match="turned at most"):
        turn_axis(relative_motions(invert(_readings([0, 0.5, 1.0]))))
