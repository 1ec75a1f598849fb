"""Tracker uncertainty carried along the transform chain to the poses the correction works with.

A tracker reading ``T_C_T`` comes with a 6x6 covariance ordered (position mm^2 of the target origin, then
orientation rad^2), both in camera axes; the orientation error turns the whole target about its origin.
Scan covariances are stated for the scan origin in world axes, as ``refine.ScanPrior`` expects.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike


def skew(v: ArrayLike) -> np.ndarray:
    """(..., 3) vectors -> (..., 3, 3) cross-product matrices ``[v]x`` (``skew(v) @ u == cross(v, u)``)."""
    v = np.asarray(v, dtype=float)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2], S[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    S[..., 1, 0], S[..., 2, 0], S[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return S


def scan_pose_covariance(T_W_C: ArrayLike, T_C_T: ArrayLike, T_T_S: ArrayLike, reading_cov: ArrayLike) -> np.ndarray:
    """6x6 covariance of ``T_W_S = T_W_C T_C_T T_T_S`` (t mm^2 at the scan origin, r rad^2; world axes).

    First order: a target rotation ``dr`` moves the scan origin by ``dr x (R_C_T t_T_S)``.
    """
    T_W_C, T_C_T, T_T_S = (np.asarray(a, float) for a in (T_W_C, T_C_T, T_T_S))
    C_C = covariance_about(reading_cov, np.zeros(3), T_C_T[:3, :3] @ T_T_S[:3, 3])   # target -> scan origin
    return _to_world(T_W_C, C_C)


def _to_world(T_W_C: ArrayLike, covariance: ArrayLike) -> np.ndarray:
    """A 6x6 (t, r) covariance in camera axes, turned into world axes."""
    R = np.kron(np.eye(2), np.asarray(T_W_C, float)[:3, :3])
    return R @ np.asarray(covariance, float) @ R.T


def transfer_covariance(T_W_C_before: ArrayLike, cov_before: ArrayLike, T_W_C_after: ArrayLike, cov_after: ArrayLike
                        ) -> np.ndarray:
    """6x6 error of one coordinate transfer (Eq. 2) as a world motion of the new station about the still
    target's origin (t mm^2, r rad^2; world axes).

    The reading before the move misplaces the target in W by its own error (camera axes of the old station);
    the reading after it misplaces the new camera about the target by the opposite of its error (camera
    axes of the new station). Both are independent, so their covariances, turned into world axes, add.
    """
    return _to_world(T_W_C_before, cov_before) + _to_world(T_W_C_after, cov_after)


def arm_repeatability_covariance(sigma_mm: float, sigma_rad: float, flange_to_target_W_mm: ArrayLike) -> np.ndarray:
    """6x6 covariance of the target's pose error one arm move's repeatability gives (t mm^2 of the target origin,
    r rad^2; world axes): an isotropic flange offset (1-sigma ``sigma_mm`` per axis, ``sigma_rad`` per axis, any
    axes alike) whose rotation moves the target origin, ``flange_to_target_W_mm`` (world axes) away, by its lever."""
    C = np.diag([sigma_mm**2] * 3 + [sigma_rad**2] * 3)
    return covariance_about(C, np.zeros(3), flange_to_target_W_mm)


def recentre(centre_mm: ArrayLike, new_centre_mm: ArrayLike) -> np.ndarray:
    """6x6 map of a small world motion (t mm, r rad) about ``centre_mm`` to the same motion about
    ``new_centre_mm`` (a rotation ``r`` moves the new centre by ``r x (new - old)``)."""
    J = np.eye(6)
    J[:3, 3:] = -skew(np.asarray(new_centre_mm, float) - np.asarray(centre_mm, float))
    return J


def covariance_about(covariance: ArrayLike, centre_mm: ArrayLike, new_centre_mm: ArrayLike) -> np.ndarray:
    """The 6x6 covariance of a small world motion about ``centre_mm``, stated about ``new_centre_mm``."""
    J = recentre(centre_mm, new_centre_mm)
    return J @ np.asarray(covariance, float) @ J.T
