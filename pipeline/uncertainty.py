"""Tracker uncertainty carried along the transform chain to the poses the correction works with.

A tracker reading ``T_C_T`` comes with a 6x6 covariance ordered (position mm^2 of the target origin, then
orientation rad^2), both in camera axes; the orientation error turns the whole target about its origin.
Scan covariances are stated for the scan origin in world axes, as ``refine.ScanPrior`` expects.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def scan_pose_covariance(T_W_C: ArrayLike, T_C_T: ArrayLike, T_T_S: ArrayLike, reading_cov: ArrayLike) -> np.ndarray:
    """6x6 covariance of ``T_W_S = T_W_C T_C_T T_T_S`` (t mm^2 at the scan origin, r rad^2; world axes).

    First order: a target rotation ``dr`` moves the scan origin by ``dr x (R_C_T t_T_S)``.
    """
    T_W_C, T_C_T, T_T_S = (np.asarray(a, float) for a in (T_W_C, T_C_T, T_T_S))
    C = np.asarray(reading_cov, float)
    lever_C = T_C_T[:3, :3] @ T_T_S[:3, 3]
    J = np.zeros((6, 6))
    J[:3, :3] = np.eye(3)
    J[:3, 3:] = -_skew(lever_C)
    J[3:, 3:] = np.eye(3)
    R = np.kron(np.eye(2), T_W_C[:3, :3])
    return R @ J @ C @ J.T @ R.T


def transfer_covariance(reading_cov: ArrayLike, lever_mm: float) -> np.ndarray:
    """6x6 error of one coordinate transfer (two readings of the still target), about a point ``lever_mm``
    from the target, isotropic in direction (t mm^2, r rad^2)."""
    C = np.asarray(reading_cov, float)
    var_t = 2.0 * float(np.trace(C[:3, :3])) / 3.0
    var_r = 2.0 * float(np.trace(C[3:, 3:])) / 3.0
    return np.diag([var_t + var_r * lever_mm**2] * 3 + [var_r] * 3)
