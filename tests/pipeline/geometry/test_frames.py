"""SE(3) identities and the transform chain (docs/architecture.md, "Frames")."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from tandemscan.pipeline.geometry import frames as F

finite = st.floats(-5000, 5000, allow_nan=False)
angles = st.floats(-np.pi, np.pi, allow_nan=False)
poses = st.builds(
    lambda x, y, z, a, b, c: F.from_rotvec((x, y, z), np.array([a, b, c]) * 0.9),
    finite, finite, finite, angles, angles, angles,
)


@settings(max_examples=60, deadline=None)
@given(poses)
def test_inverse_is_two_sided(T):
    np.testing.assert_allclose(F.invert(T) @ T, np.eye(4), atol=1e-9)
    np.testing.assert_allclose(T @ F.invert(T), np.eye(4), atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(poses, poses, poses)
def test_compose_is_associative_and_inverts_in_reverse(A, B, C):
    np.testing.assert_allclose(F.compose(A, B, C), A @ (B @ C), atol=1e-6)
    np.testing.assert_allclose(F.invert(F.compose(A, B)), F.compose(F.invert(B), F.invert(A)), atol=1e-6)


@settings(max_examples=60, deadline=None)
@given(poses)
def test_round_trips_through_every_parameterisation(T):
    t, rv = F.to_rotvec(T)
    np.testing.assert_allclose(F.from_rotvec(t, rv), T, atol=1e-9)
    t, rpy = F.to_rpy(T)
    np.testing.assert_allclose(F.from_rpy(t, rpy), T, atol=1e-9)
    t, q = F.to_quaternion(T)
    assert q[3] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
    np.testing.assert_allclose(F.from_quaternion(t, q), T, atol=1e-9)


def test_rpy_is_jaka_fixed_axes_xyz():
    """JAKA reports rx, ry, rz applied about fixed x, then y, then z: R = Rz Ry Rx."""
    rx, ry, rz = 0.3, -0.2, 1.1
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    np.testing.assert_allclose(F.from_rpy((0, 0, 0), (rx, ry, rz))[:3, :3], Rz @ Ry @ Rx, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(poses, poses, poses)
def test_coordinate_transfer_keeps_target_world_pose(T_W_C_old, T_C_T_old, T_C_T_new):
    """Eq. 2: after the transfer, the new camera pose sees the same target world pose."""
    T_W_T = T_W_C_old @ T_C_T_old
    T_W_C_new = F.coordinate_transfer(T_W_C_old, T_C_T_old, T_C_T_new)
    np.testing.assert_allclose(T_W_C_new @ T_C_T_new, T_W_T, atol=1e-6)


@settings(max_examples=40, deadline=None)
@given(poses, poses, poses, poses)
def test_agv_world_poses_close_the_chain(T_W_V2, T_V2_B, T_B_E, T_E_T):
    """Eq. 3-5 recover the measurement chassis' pose from the target's world pose."""
    T_W_T = F.compose(T_W_V2, T_V2_B, T_B_E, T_E_T)
    np.testing.assert_allclose(F.measurement_agv_in_world(T_W_T, T_V2_B, T_B_E, T_E_T), T_W_V2, atol=1e-5)


def test_pose_error_reports_translation_and_angle():
    T = F.from_rotvec((10, 0, 0), (0, 0, 0.01))
    err_mm, err_rad = F.pose_error(T, np.eye(4))
    assert abs(err_mm - 10) < 1e-12 and abs(err_rad - 0.01) < 1e-12
