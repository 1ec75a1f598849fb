"""Self-calibration of the scanner mount in the pose graph (docs/calibration.md, "Self-calibration in the job's
pose graph").

Every scan is placed by ``T_W_S_i = T_W_C T_C_T_i X`` with one shared ``X = T_T_S``, so an error of X is the
same right-perturbation ``D`` (a motion in the scanner frame S) of every scan, ``T_W_S_i -> T_W_S_i D``. In the
world it shows differently for each target orientation, so overlaps between scans taken at different
orientations measure it. ``D`` is one more unknown of ``pose_graph.refine_poses`` with the calibration's
covariance as its prior (:class:`MountPrior`); the result (:class:`MountEstimate`) reports its estimate, its
posterior covariance and the information the scans alone give on it. Order of every 6-vector and 6x6 here:
translation (mm) first, then rotation vector (rad).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class MountPrior:
    """Prior of the shared scanner-mount correction ``D`` (``X = T_T_S -> X D``): 6x6 covariance, order
    (t mm^2, rotation vector rad^2), a motion in the scanner frame S about its origin.

    Only the directions the overlaps observe are estimated: those whose data information is at least
    ``min_information_ratio`` times the prior's (eigen-directions of the data information in prior-whitened
    coordinates); the others stay at the prior (zero correction, prior variance)."""

    covariance: np.ndarray
    min_information_ratio: float = 1.0


@dataclass(frozen=True)
class MountEstimate:
    """The estimated shared mount correction.

    ``correction``: the 4x4 ``D`` (refined ``T_T_S = T_T_S D``); ``covariance``: its 6x6 posterior (t mm^2,
    r rad^2; scanner frame S); ``data_information``: the 6x6 information the overlaps alone give on it, the
    other unknowns marginalised (same order); ``information_ratio``: per eigen-direction of that information
    in prior-whitened coordinates (ascending) the data's information over the prior's, the directions being
    the columns of ``whitened_directions`` (:meth:`observability` turns them into directions of D);
    ``estimated``: how many of them were estimated (the rest were held at the prior)."""

    correction: np.ndarray
    covariance: np.ndarray
    prior_covariance: np.ndarray
    data_information: np.ndarray
    information_ratio: np.ndarray
    whitened_directions: np.ndarray
    estimated: int

    def observability(self, lever_mm: float) -> dict:
        """Figures for a report (mm, deg): the correction, its prior and posterior 1-sigma per axis of S,
        and per prior-whitened eigen-direction (weakest first) the ratio of data to prior information with
        the direction as a unit 6-vector (t mm, rotation as mm at ``lever_mm``)."""
        L = np.linalg.cholesky(self.prior_covariance)
        dirs = (L @ self.whitened_directions).T * np.r_[[1.0] * 3, [lever_mm] * 3]
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        t, r = self.correction[:3, 3], Rotation.from_matrix(self.correction[:3, :3]).as_rotvec()
        sig = np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
        sig0 = np.sqrt(np.clip(np.diag(self.prior_covariance), 0.0, None))
        return {
            "correction_mm": t.tolist(),
            "correction_deg": np.degrees(r).tolist(),
            "prior_sigma_mm": sig0[:3].tolist(),
            "prior_sigma_deg": np.degrees(sig0[3:]).tolist(),
            "sigma_mm": sig[:3].tolist(),
            "sigma_deg": np.degrees(sig[3:]).tolist(),
            "information_ratio": self.information_ratio.tolist(),
            "directions": dirs.tolist(),
            "lever_mm": lever_mm,
            "estimated_directions": self.estimated,
        }


@dataclass(frozen=True)
class MountSolve:
    """How the mount was solved: ``D = L u`` with the prior ``u ~ N(0, I)``, ``u = basis z`` estimated;
    the data's information ratios and eigen-directions in u; the data information on D; the prior."""

    L: np.ndarray
    basis: np.ndarray
    ratio: np.ndarray
    directions: np.ndarray
    data_information: np.ndarray
    prior: np.ndarray


def schur(J: np.ndarray, first: int) -> np.ndarray:
    """Information ``J^T J`` of the columns from ``first`` on, the columns before them marginalised."""
    H = J.T @ J
    A, B, C = H[:first, :first], H[:first, first:], H[first:, first:]
    return C - B.T @ np.linalg.solve(A, B)
