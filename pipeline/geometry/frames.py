"""SE(3) helpers and the transform chain of docs/architecture.md ("Frames").

All transforms are 4x4 float64 homogeneous matrices in millimetres; ``T_a_b`` maps coordinates in frame
``b`` into frame ``a`` so that ``T_a_c = T_a_b @ T_b_c``. Angles are radians. Roll-pitch-yaw follows the
JAKA convention: fixed axes x, then y, then z, i.e. ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation
from tandemscan.pipeline.geometry.uncertainty import recentre

# ---------------------------------------------------------------- building and taking apart


def make_transform(rotation: ArrayLike, translation_mm: ArrayLike) -> np.ndarray:
    """4x4 from a 3x3 rotation matrix and a translation (mm)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(rotation, dtype=float)
    T[:3, 3] = np.asarray(translation_mm, dtype=float)
    return T


def invert(T: ArrayLike) -> np.ndarray:
    """Inverse of a rigid transform (exact, no general matrix inverse). Works on (..., 4, 4) stacks."""
    T = np.asarray(T, dtype=float)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Ti = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    Ti[..., :3, :3] = Rt
    Ti[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    Ti[..., 3, 3] = 1.0
    return Ti


def compose(*transforms: ArrayLike) -> np.ndarray:
    """Product ``T1 @ T2 @ ...`` (left to right, as the frames chain)."""
    out = np.eye(4)
    for T in transforms:
        out = out @ np.asarray(T, dtype=float)
    return out


def from_rotvec(translation_mm: ArrayLike, rotvec_rad: ArrayLike) -> np.ndarray:
    """4x4 from a translation (mm) and a rotation vector (axis times angle, rad)."""
    return make_transform(Rotation.from_rotvec(np.asarray(rotvec_rad, float)).as_matrix(), translation_mm)


def to_rotvec(T: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """(translation mm, rotation vector rad) of a 4x4."""
    T = np.asarray(T, dtype=float)
    return T[:3, 3].copy(), Rotation.from_matrix(T[:3, :3]).as_rotvec()


def from_rpy(translation_mm: ArrayLike, rpy_rad: ArrayLike) -> np.ndarray:
    """4x4 from a translation (mm) and JAKA roll-pitch-yaw (rad, fixed axes x-y-z)."""
    return make_transform(Rotation.from_euler("xyz", np.asarray(rpy_rad, float)).as_matrix(), translation_mm)


def to_rpy(T: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """(translation mm, JAKA roll-pitch-yaw rad) of a 4x4."""
    T = np.asarray(T, dtype=float)
    return T[:3, 3].copy(), Rotation.from_matrix(T[:3, :3]).as_euler("xyz")


def from_quaternion(translation_mm: ArrayLike, quaternion_xyzw: ArrayLike) -> np.ndarray:
    """4x4 from a translation (mm) and a unit quaternion, scalar last (x, y, z, w)."""
    return make_transform(Rotation.from_quat(np.asarray(quaternion_xyzw, float)).as_matrix(), translation_mm)


def to_quaternion(T: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """(translation mm, quaternion x y z w with w >= 0) of a 4x4."""
    T = np.asarray(T, dtype=float)
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    return T[:3, 3].copy(), q if q[3] >= 0 else -q


def planar_pose(x_mm: float, y_mm: float, heading_rad: float, z_mm: float = 0.0) -> np.ndarray:
    """4x4 of a chassis on the floor: position (mm) and heading about +z (rad)."""
    return make_transform(Rotation.from_euler("z", heading_rad).as_matrix(), (x_mm, y_mm, z_mm))


def orthonormalize(T: ArrayLike) -> np.ndarray:
    """Nearest proper rigid transform (SVD projection of the rotation block)."""
    T = np.array(T, dtype=float)
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    T[:3, :3] = R
    T[3] = (0, 0, 0, 1)
    return T


# ---------------------------------------------------------------- applying and comparing


def transform_points(T: ArrayLike, points_mm: ArrayLike) -> np.ndarray:
    """Apply ``T`` to an (N, 3) array of points (mm)."""
    T = np.asarray(T, dtype=float)
    P = np.asarray(points_mm, dtype=float)
    return np.einsum("ij,...j->...i", T[:3, :3], P) + T[:3, 3]  # BLAS's (N, 3) @ (3, 3) is ~15x slower


def rotate_vectors(T: ArrayLike, vectors: ArrayLike) -> np.ndarray:
    """Apply only the rotation of ``T`` to (N, 3) directions (normals)."""
    T = np.asarray(T, dtype=float)
    return np.einsum("ij,...j->...i", T[:3, :3], np.asarray(vectors, dtype=float))


def rotation_angle(T_or_R: ArrayLike) -> float:
    """Angle (rad) of the rotation part, in [0, pi]."""
    R = np.asarray(T_or_R, dtype=float)[:3, :3]
    return float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))


def pose_error(T_estimate: ArrayLike, T_truth: ArrayLike) -> tuple[float, float]:
    """(translation error mm, rotation error rad) between two poses of the same frame."""
    D = invert(T_truth) @ np.asarray(T_estimate, dtype=float)
    return float(np.linalg.norm(np.asarray(T_estimate)[:3, 3] - np.asarray(T_truth)[:3, 3])), rotation_angle(D)


# ---------------------------------------------------------------- the cell's transform chain


def coordinate_transfer(T_W_C_old: ArrayLike, T_C_T_old: ArrayLike, T_C_T_new: ArrayLike) -> np.ndarray:
    """Eq. 2: the tracker's new world pose after it moved while the target stood still.

    ``T_W_T = T_W_C_old T_C_T_old`` and ``T_W_C_new = T_W_T inv(T_C_T_new)``.
    """
    return compose(T_W_C_old, T_C_T_old, invert(T_C_T_new))


@dataclass(frozen=True)
class PoseTransfer:
    """A coordinate transfer's result: the tracker's new world pose ``T_W_C`` (4x4 mm) and its error, a world
    motion about ``centre_mm`` (W, mm) with ``covariance`` (6x6, t mm^2 then r rad^2; world axes)."""

    T_W_C: np.ndarray
    centre_mm: np.ndarray
    covariance: np.ndarray


def _world_motion(translation_mm: np.ndarray, rotvec_rad: np.ndarray, centre_mm: np.ndarray) -> np.ndarray:
    """4x4 of a small world motion: the rotation ``rotvec_rad`` about ``centre_mm``, then ``translation_mm``."""
    M = from_rotvec(np.zeros(3), rotvec_rad)
    M[:3, 3] = centre_mm - M[:3, :3] @ centre_mm + translation_mm
    return M


def coordinate_transfer_poses(T_W_C_old: ArrayLike, before_T_C_T: list[np.ndarray], after_T_C_T: list[np.ndarray],
                              covariances: list[np.ndarray], iterations: int = 5) -> PoseTransfer:
    """Eq. 2 over several target poses: the tracker's new world pose from the still target read at ``K`` poses
    before (``before_T_C_T``, old camera) and after (``after_T_C_T``, new camera) it moved, pair ``j`` the same
    pose. Each pair places the target in W twice (``T_W_C_old T_C_T_before`` and ``T_W_C_new T_C_T_after``); their
    difference, a world motion about that target's origin (t mm, rotation vector rad), has the 6x6 covariance
    ``covariances[j]`` (world axes: both readings' and, where the arm moved between them, its repeatability's).
    The estimate minimises the whitened differences (Gauss-Newton from pair 0's Eq. 2), so the target positions,
    spread over the arm's reach, fix the rotation where one target's orientation would; its covariance (the
    inverse normal matrix) is stated about the targets' centroid. One pair gives Eq. 2 and its covariance exactly.
    """
    T_W_C_old = np.asarray(T_W_C_old, float)
    X = [T_W_C_old @ np.asarray(b, float) for b in before_T_C_T]  # the target in W, read from the old station
    B = [np.asarray(a, float) for a in after_T_C_T]
    W = [np.linalg.inv(np.asarray(c, float)) for c in covariances]
    centre = np.mean([x[:3, 3] for x in X], axis=0)
    T = X[0] @ invert(B[0])
    for _ in range(iterations):
        N, g = np.zeros((6, 6)), np.zeros(6)
        for Xj, Bj, Wj in zip(X, B, W, strict=True):
            P = T @ Bj
            delta = np.r_[Xj[:3, 3] - P[:3, 3], Rotation.from_matrix(Xj[:3, :3] @ P[:3, :3].T).as_rotvec()]
            J = recentre(centre, P[:3, 3])
            N += J.T @ Wj @ J
            g += J.T @ Wj @ delta
        xi = np.linalg.solve(N, g)
        T = _world_motion(xi[:3], xi[3:], centre) @ T
        if np.linalg.norm(xi[:3]) < 1e-9 and np.linalg.norm(xi[3:]) < 1e-12:
            break
    return PoseTransfer(orthonormalize(T), centre, np.linalg.inv(N))


def measurement_agv_in_world(
    T_W_T: ArrayLike, T_V2_B: ArrayLike, T_B_E: ArrayLike, T_E_T: ArrayLike
) -> np.ndarray:
    """Eq. 3-5: ``T_W_V2 = T_W_T inv(T_V2_B T_B_E T_E_T)``."""
    return compose(T_W_T, invert(compose(T_V2_B, T_B_E, T_E_T)))


def mean_pose(transforms: list[np.ndarray]) -> np.ndarray:
    """Average of nearby poses: mean translation (mm) and the chordal L2 mean rotation."""
    Ts = np.asarray(transforms, dtype=float)
    return make_transform(Rotation.from_matrix(Ts[:, :3, :3]).mean().as_matrix(), Ts[:, :3, 3].mean(axis=0))
