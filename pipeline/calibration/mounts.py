"""Mount calibration from chassis turns in place: ``T_V1_C`` (tracker) and ``T_V2_B`` (arm base).

When a chassis turns in place, every frame M mounted on it rotates about the chassis' vertical axis, which
passes through the chassis origin. The relative motions ``inv(T_X_M[0]) T_X_M[k]`` of M, measured from any
frame X that stands still, are rotations about that axis written in M: their common axis gives the mount's
roll and pitch, their common fixed line the distance of M's origin from the chassis axis. A turn says
nothing about the height of M on the chassis (along the axis), nor about a rotation of the whole mount
about that axis (its yaw together with the bearing of its x, y position): those stay nominal
(docs/calibration.md). All mm and rad.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation
from tandemscan.pipeline.calibration.hand_eye import HandEyeResult, solve_hand_eye
from tandemscan.pipeline.geometry.frames import invert, make_transform

log = logging.getLogger(__name__)


class MountError(ValueError):
    """Turn data that cannot calibrate a mount; the message says why."""


@dataclass(frozen=True)
class TurnAxis:
    """The chassis' vertical axis seen from the mounted frame M: unit direction and the point of the axis
    nearest M's origin (mm), with the RMS misfit of the motions to one fixed axis (mm, rad)."""

    direction: np.ndarray
    point_mm: np.ndarray
    line_rms_mm: float
    axis_rms_rad: float


def relative_motions(T_X_M: ArrayLike) -> np.ndarray:
    """``inv(T_X_M[0]) T_X_M[k]`` for k >= 1: the motions of M in its own first frame."""
    T = np.asarray(T_X_M, dtype=float)
    return invert(T[0])[None] @ T[1:]


def turn_axis(motions_M: ArrayLike, min_turn_rad: float = np.radians(2.0)) -> TurnAxis:
    """The common rotation axis of motions of M (each ``inv(T_X_M0) T_X_Mk``), in frame M.

    The direction is the angle-weighted mean of the motions' axes (sign: the first motion's), the point the
    least-squares solution of ``(R_k - I) p = -t_k`` nearest M's origin.
    """
    Mk = np.asarray(motions_M, dtype=float)
    if Mk.ndim != 3 or Mk.shape[1:] != (4, 4) or len(Mk) < 1:
        raise MountError(f"need at least one 4x4 motion, got shape {Mk.shape}")
    rv = Rotation.from_matrix(Mk[:, :3, :3]).as_rotvec()
    ang = np.linalg.norm(rv, axis=1)
    keep = ang >= min_turn_rad
    if not np.any(keep):
        raise MountError(
            f"the chassis turned at most {np.degrees(ang.max()):.2f} deg: turn by {np.degrees(min_turn_rad):.0f} "
            "deg or more"
        )
    Mk, rv, ang = Mk[keep], rv[keep], ang[keep]
    axes = rv / ang[:, None]
    ref = axes[0]
    axes = np.where((axes @ ref)[:, None] < 0, -axes, axes)
    direction = (ang[:, None] * axes).sum(axis=0)
    direction /= np.linalg.norm(direction)
    axis_rms = float(np.sqrt(np.mean(np.arccos(np.clip(axes @ direction, -1, 1)) ** 2)))
    A = (Mk[:, :3, :3] - np.eye(3)).reshape(-1, 3)
    b = -Mk[:, :3, 3].reshape(-1)
    # the system is blind along the axis: fix that component by the minimum-norm solution
    p, *_ = np.linalg.lstsq(A, b, rcond=1e-6)
    p -= (p @ direction) * direction
    line_rms = float(np.sqrt(np.mean((A @ p - b) ** 2)))
    return TurnAxis(direction, p, line_rms, axis_rms)


def _min_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation taking unit vector ``a`` onto unit vector ``b``."""
    v = np.cross(a, b)
    s, c = np.linalg.norm(v), float(a @ b)
    if s < 1e-15:
        return np.eye(3)
    return Rotation.from_rotvec(v / s * np.arctan2(s, c)).as_matrix()


def mount_from_turns(motions_M: ArrayLike, T_V_M_nominal: ArrayLike) -> tuple[np.ndarray, TurnAxis]:
    """Mount ``T_V_M`` from turn-in-place motions of M.

    Measured: roll and pitch (the chassis axis in M) and the distance of M from the chassis axis. Nominal:
    height z, and the rotation about the chassis axis (yaw, which also turns the x, y position about the
    axis). The chassis axis is +z of V; the measured axis is signed to agree with the nominal prediction.
    """
    T_nom = np.asarray(T_V_M_nominal, dtype=float)
    ax = turn_axis(motions_M)
    a_nom = T_nom[:3, :3].T @ np.array([0.0, 0.0, 1.0])  # chassis z seen from M, nominally
    a = ax.direction if ax.direction @ a_nom >= 0 else -ax.direction
    R = T_nom[:3, :3] @ _min_rotation(a, a_nom)  # R a = e_z, yaw as close to nominal as it gets
    Rp = R @ ax.point_mm
    t = np.array([-Rp[0], -Rp[1], T_nom[2, 3]])
    return make_transform(R, t), TurnAxis(a, ax.point_mm, ax.line_rms_mm, ax.axis_rms_rad)


def solve_flange_mount(T_B_E: ArrayLike, T_C_T: ArrayLike, T_T_S: ArrayLike) -> HandEyeResult:
    """``T_E_S`` (scanner on the flange) from arm poses and tracker readings, with ``T_T_S`` known.

    ``T_C_T[i] T_T_S = T_C_B T_B_E[i] T_E_S`` with the camera and the arm base still: a second ``A X = X B``
    whose "plate" is the tracker camera (``T_S_C = inv(T_C_T T_T_S)``). Its accuracy is that of the arm's
    kinematic model.
    """
    T_S_C = invert(np.asarray(T_C_T, dtype=float) @ np.asarray(T_T_S, dtype=float))
    return solve_hand_eye(np.asarray(T_B_E, dtype=float), T_S_C, method="park")


def arm_base_motions(T_C_T: ArrayLike, T_B_T: ArrayLike) -> np.ndarray:
    """Motions of the arm base B in its own frame while its chassis turns with the arm still.

    ``T_B_T`` is the target in the base frame at the arm's pose (``T_B_E T_E_S inv(T_T_S)``).
    """
    T_B_T = np.asarray(T_B_T, dtype=float)
    return T_B_T[None] @ relative_motions(T_C_T) @ invert(T_B_T)[None]
