"""Hand-eye calibration ``A X = X B`` (Eq. 9-12): the scanner on the tracker target, ``X = T_T_S``.

At arm pose i the tracker reads ``T_C_T[i]`` and a plate scan gives ``T_S_P[i]``. Camera and plate stand
still, so ``T_C_T[i] X T_S_P[i] = T_C_P`` for every i, and for a pair (i, j)::

    A = inv(T_C_T[j]) T_C_T[i],   B = T_S_P[j] inv(T_S_P[i]),   A X = X B.

Closed-form solvers: ``tsai`` (Tsai-Lenz, modified Rodrigues parameters), ``park`` (Park-Martin, rotation
logarithms aligned in the least-squares sense), ``horaud`` (Horaud-Dornaika, unit quaternion as the smallest
eigenvector of a 4x4 quadratic form), ``daniilidis`` (dual quaternions, rotation and translation at once).
``refine`` is the maximum-likelihood estimate: starting from the closed-form answer that fits the data best,
it minimises the distance of every plate point, carried into the tracker frame C through its pose's chain,
to that point's common position, jointly over X and the plate's fixed points in C, each pose's residual
whitened by the covariance both noise sources give it (tracker reading and plate fit). All in mm and
radians; residuals also in deg.
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation
from tandemscan.pipeline.geometry.frames import invert, make_transform
from tandemscan.pipeline.geometry.uncertainty import skew

log = logging.getLogger(__name__)

Method = Literal["tsai", "park", "horaud", "daniilidis", "refine"]
CLOSED_FORM: tuple[str, ...] = ("tsai", "park", "horaud", "daniilidis")
METHODS: tuple[str, ...] = (*CLOSED_FORM, "refine")

#: plate points (frame P, mm) used when the caller gives none: a tetrahedron the size of the plate
#: 1-sigma (translation mm, rotation rad) per axis of a tracker reading about 3 m away (TrackerConfig defaults)
DEFAULT_TRACKER_SIGMA = (0.025, float(np.radians(0.0025)))
DEFAULT_PLATE_POINTS_P = np.array([[-100.0, 0.0, 0.0], [100.0, 0.0, 0.0], [0.0, 100.0, 0.0], [0.0, 0.0, 100.0]])


class HandEyeError(ValueError):
    """Bad or degenerate hand-eye input; the message says what is wrong with the data."""


@dataclass(frozen=True)
class HandEyeResult:
    """Solution ``T_T_S`` (4x4, mm) of ``A X = X B`` with its residuals and uncertainty.

    - ``pairs``: the (i, j) pose pairs used; ``rot_residuals_deg`` / ``trans_residuals_mm`` per pair:
      angle and translation of ``inv(A X) X B``'s mismatch.
    - ``point_residuals_mm``: per pose, RMS distance of its plate points in frame C from their common
      position (the reprojection error in the world).
    - ``T_C_P``: the plate in the tracker camera frame implied by the solution.
    - ``covariance``: 6x6 of ``X`` in its own frame, order (translation mm, rotation vector rad) as every
      covariance of the project (``X -> X [R(r), t]``), from the refinement's Jacobian scaled by the residual
      variance; ``sigma_trans_mm`` / ``sigma_rot_deg`` its 1-sigma per axis.
    """

    T_T_S: np.ndarray
    method: str
    pairs: list[tuple[int, int]]
    rot_residuals_deg: np.ndarray
    trans_residuals_mm: np.ndarray
    point_residuals_mm: np.ndarray
    T_C_P: np.ndarray
    covariance: np.ndarray
    rejected_pairs: int

    @property
    def sigma_rot_deg(self) -> np.ndarray:
        """1-sigma rotation uncertainty per axis of frame T (deg)."""
        return np.degrees(np.sqrt(np.clip(np.diag(self.covariance)[3:], 0.0, None)))

    @property
    def sigma_trans_mm(self) -> np.ndarray:
        """1-sigma translation uncertainty per axis (mm)."""
        return np.sqrt(np.clip(np.diag(self.covariance)[:3], 0.0, None))

    @property
    def point_rms_mm(self) -> float:
        """RMS of all plate-point residuals in frame C (mm)."""
        return float(np.sqrt(np.mean(self.point_residuals_mm**2)))

    def summary(self) -> dict[str, float | str | int]:
        """Plain numbers for reports and JSON."""
        return {
            "method": self.method,
            "pairs": len(self.pairs),
            "rejected_pairs": self.rejected_pairs,
            "rot_residual_rms_deg": float(np.sqrt(np.mean(self.rot_residuals_deg**2))),
            "trans_residual_rms_mm": float(np.sqrt(np.mean(self.trans_residuals_mm**2))),
            "point_rms_mm": self.point_rms_mm,
            "sigma_rot_deg": float(np.linalg.norm(self.sigma_rot_deg)),
            "sigma_trans_mm": float(np.linalg.norm(self.sigma_trans_mm)),
        }


# ---------------------------------------------------------------- input and pairs


def _as_poses(poses: ArrayLike, name: str) -> np.ndarray:
    T = np.asarray(poses, dtype=float)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise HandEyeError(f"{name} must be a sequence of 4x4 matrices, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise HandEyeError(f"{name} contains NaN or inf")
    R = T[:, :3, :3]
    err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((err > 1e-6) | (np.linalg.det(R) < 0))
    if len(bad):
        raise HandEyeError(f"{name}[{int(bad[0])}] is not a rigid transform (rotation not orthonormal)")
    return T


def _relative_motions(
    T_C_T: np.ndarray, T_S_P: np.ndarray, min_rot_rad: float
) -> tuple[list[tuple[int, int]], np.ndarray, np.ndarray, int]:
    """All pose pairs whose tracker-side rotation is at least ``min_rot_rad``: (pairs, A, B, n_rejected)."""
    ij = np.array(list(itertools.combinations(range(len(T_C_T)), 2))).reshape(-1, 2)
    A = invert(T_C_T)[ij[:, 1]] @ T_C_T[ij[:, 0]]
    B = T_S_P[ij[:, 1]] @ invert(T_S_P)[ij[:, 0]]
    keep = np.linalg.norm(Rotation.from_matrix(A[:, :3, :3]).as_rotvec(), axis=1) >= min_rot_rad
    pairs = [(int(i), int(j)) for i, j in ij[keep]]
    return pairs, A[keep], B[keep], int(np.sum(~keep))


def _check_conditioning(A: np.ndarray, min_axis_spread_deg: float) -> None:
    """Raise when the relative rotations do not span at least two axes."""
    if len(A) < 2:
        raise HandEyeError(
            f"only {len(A)} pose pair(s) rotate enough: move the arm through larger rotations about different axes"
        )
    rv = Rotation.from_matrix(A[:, :3, :3]).as_rotvec()
    ang = np.linalg.norm(rv, axis=1)
    axes = rv / ang[:, None]
    M = np.einsum("n,ni,nj->ij", ang, axes, axes) / ang.sum()
    ev = np.linalg.eigvalsh(M)
    spread_deg = float(np.degrees(np.arcsin(np.sqrt(max(ev[1], 0.0) / max(ev[2], 1e-300)))))
    if spread_deg < min_axis_spread_deg:
        raise HandEyeError(
            f"degenerate poses: all relative rotations are about one axis (spread {spread_deg:.2f} deg < "
            f"{min_axis_spread_deg} deg); X is unobservable along it: add rotations about other axes"
        )


# ---------------------------------------------------------------- closed-form solvers


def _translation_ls(A: np.ndarray, B: np.ndarray, R_X: np.ndarray) -> np.ndarray:
    """Least squares of ``(R_A - I) t_X = R_X t_B - t_A`` (mm)."""
    M = (A[:, :3, :3] - np.eye(3)).reshape(-1, 3)
    rhs = (np.einsum("ij,nj->ni", R_X, B[:, :3, 3]) - A[:, :3, 3]).reshape(-1)
    t, *_ = np.linalg.lstsq(M, rhs, rcond=None)
    return t


def _solve_tsai(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Tsai-Lenz: ``skew(Pa + Pb) Px' = Pb - Pa`` with ``P = 2 sin(theta/2) axis``, ``Px' = tan(theta/2) axis``."""
    ra = Rotation.from_matrix(A[:, :3, :3]).as_rotvec()
    rb = Rotation.from_matrix(B[:, :3, :3]).as_rotvec()

    def mrp(rv: np.ndarray) -> np.ndarray:
        th = np.linalg.norm(rv, axis=1, keepdims=True)
        return 2.0 * np.sin(th / 2.0) * rv / np.maximum(th, 1e-300)

    pa, pb = mrp(ra), mrp(rb)
    px_, *_ = np.linalg.lstsq(skew(pa + pb).reshape(-1, 3), (pb - pa).reshape(-1), rcond=None)
    # Px' = tan(theta/2) axis  ->  quaternion (cos, sin axis) proportional to (1, Px')
    q = np.append(px_, 1.0)
    R_X = Rotation.from_quat(q / np.linalg.norm(q)).as_matrix()
    return make_transform(R_X, _translation_ls(A, B, R_X))


def _solve_park(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Park-Martin: ``log R_A = R_X log R_B`` solved as an orthogonal Procrustes problem."""
    alpha = Rotation.from_matrix(A[:, :3, :3]).as_rotvec()
    beta = Rotation.from_matrix(B[:, :3, :3]).as_rotvec()
    R_X = _procrustes(beta.T @ alpha)
    return make_transform(R_X, _translation_ls(A, B, R_X))


def _procrustes(H: np.ndarray) -> np.ndarray:
    """Rotation R maximising ``trace(R H)`` (H = sum of ``src dst^T``): the best ``dst ~ R src``."""
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    return Vt.T @ D @ U.T


def _quaternions(R: np.ndarray) -> np.ndarray:
    """(N, 4) unit quaternions, scalar first and >= 0, of a stack of rotation matrices."""
    q = Rotation.from_matrix(R).as_quat()[:, [3, 0, 1, 2]]
    q[q[:, 0] < 0] *= -1
    return q


def _solve_horaud(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Horaud-Dornaika: the unit quaternion x minimising ``sum |a x - x b|^2`` is the eigenvector of the
    smallest eigenvalue of ``sum (L(a) - R(b))^T (L(a) - R(b))``; then translation by least squares."""
    a, b = _quaternions(A[:, :3, :3]), _quaternions(B[:, :3, :3])
    # a x = L(a) x and x b = R(b) x with L, R the left and right multiplication matrices
    L = np.zeros((len(a), 4, 4))
    L[:, 0, 0], L[:, 0, 1:], L[:, 1:, 0] = a[:, 0], -a[:, 1:], a[:, 1:]
    L[:, 1:, 1:] = a[:, 0, None, None] * np.eye(3) + skew(a[:, 1:])
    Rm = np.zeros((len(b), 4, 4))
    Rm[:, 0, 0], Rm[:, 0, 1:], Rm[:, 1:, 0] = b[:, 0], -b[:, 1:], b[:, 1:]
    Rm[:, 1:, 1:] = b[:, 0, None, None] * np.eye(3) - skew(b[:, 1:])
    D = L - Rm
    _, V = np.linalg.eigh(np.einsum("nji,njk->ik", D, D))
    q = V[:, 0]
    R_X = Rotation.from_quat(q[[1, 2, 3, 0]]).as_matrix()
    return make_transform(R_X, _translation_ls(A, B, R_X))


def _dual_quaternion(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(real, dual) quaternions, scalar first, of a stack of 4x4 (real part with scalar >= 0)."""
    q = _quaternions(T[:, :3, :3])
    t = np.column_stack([np.zeros(len(T)), T[:, :3, 3]])
    return q, 0.5 * _qmul(t, q)


def _qmul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product of (..., 4) quaternions, scalar first."""
    p0, pv = p[..., :1], p[..., 1:]
    q0, qv = q[..., :1], q[..., 1:]
    return np.concatenate(
        [p0 * q0 - np.sum(pv * qv, axis=-1, keepdims=True), p0 * qv + q0 * pv + np.cross(pv, qv)], axis=-1
    )


def _solve_daniilidis(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Daniilidis: dual quaternions ``a q = q b``; the 2-D null space of the stacked 6x8 system, scaled so
    that ``q`` is a unit quaternion orthogonal to its dual part."""
    a, ad = _dual_quaternion(A)
    b, bd = _dual_quaternion(B)
    n = len(A)
    S = np.zeros((n, 6, 8))
    S[:, :3, 0] = a[:, 1:] - b[:, 1:]
    S[:, :3, 1:4] = skew(a[:, 1:] + b[:, 1:])
    S[:, 3:, 0] = ad[:, 1:] - bd[:, 1:]
    S[:, 3:, 1:4] = skew(ad[:, 1:] + bd[:, 1:])
    S[:, 3:, 4] = a[:, 1:] - b[:, 1:]
    S[:, 3:, 5:8] = skew(a[:, 1:] + b[:, 1:])
    _, _, Vt = np.linalg.svd(S.reshape(-1, 8), full_matrices=False)
    v1, v2 = Vt[-2], Vt[-1]
    u1, w1, u2, w2 = v1[:4], v1[4:], v2[:4], v2[4:]
    # q = l1 u1 + l2 u2 with q . q' = 0: quadratic in s = l1 / l2 (or its inverse when l2 ~ 0)
    c2, c1, c0 = u1 @ w1, u1 @ w2 + u2 @ w1, u2 @ w2
    best = None
    for s in np.roots([c2, c1, c0]) if abs(c2) > 1e-12 else [-c0 / c1]:
        if abs(np.imag(s)) > 1e-9:
            continue
        s = float(np.real(s))
        norm2 = s * s * (u1 @ u1) + 2 * s * (u1 @ u2) + u2 @ u2
        if best is None or norm2 > best[0]:
            best = (norm2, s)
    if best is None:
        raise HandEyeError("dual-quaternion solver found no real solution: poses too noisy or degenerate")
    norm2, s = best
    l2 = 1.0 / np.sqrt(norm2)
    l1 = s * l2
    q = l1 * u1 + l2 * u2
    qd = l1 * w1 + l2 * w2
    t = 2.0 * _qmul(qd, q * np.array([1.0, -1.0, -1.0, -1.0]))[1:]
    R_X = Rotation.from_quat(q[[1, 2, 3, 0]]).as_matrix()
    return make_transform(R_X, t)


_SOLVERS = {"tsai": _solve_tsai, "park": _solve_park, "horaud": _solve_horaud, "daniilidis": _solve_daniilidis}


# ---------------------------------------------------------------- refinement in the world


def _points_C(T_C_T: np.ndarray, X: np.ndarray, pts_S: np.ndarray) -> np.ndarray:
    """(N, K, 3) plate points carried into frame C through each pose's chain ``T_C_T X``."""
    M = T_C_T @ X
    return np.einsum("nij,nkj->nki", M[:, :3, :3], pts_S) + M[:, None, :3, 3]


class _Bundle:
    """Whitened residuals ``T_C_T[i] X p_ik - m_k`` (frame C, mm), X = X0 exp(dx), the K points m_k free.

    The plate stands still, so its points m_k in C are unknowns estimated jointly with X (not eliminated
    by averaging, which would weight every pose alike). Each pose's 3K residual vector is whitened by its
    covariance from both noise sources: the tracker's 6-DoF noise carried to the points
    (``dq_k = dt + dtheta x (R_C_T u_k)`` in frame C, ``u_k`` the point in frame T) and the plate points'
    own covariance in frame S (``cov_S``, (N, 3K, 3K)) turned into C. Minimising the whitened sum is the
    maximum-likelihood estimate for Gaussian noise; the weights are evaluated at ``X0``.
    """

    def __init__(self, T_C_T: np.ndarray, pts_S: np.ndarray, X0: np.ndarray, cov_C: np.ndarray,
                 cov_S: np.ndarray) -> None:
        self.T_C_T, self.pts_S, self.X0 = T_C_T, pts_S, X0
        n, self.K = pts_S.shape[:2]
        u = np.einsum("ij,nkj->nki", X0[:3, :3], pts_S) + X0[:3, 3]  # points in frame T
        lever = np.einsum("nij,nkj->nki", T_C_T[:, :3, :3], u)  # from the target origin, in frame C
        J = np.zeros((n, self.K, 3, 6))
        J[..., :3] = np.eye(3)
        J[..., 3:] = -skew(lever)
        J = J.reshape(n, 3 * self.K, 6)
        R_C_S = T_C_T[:, :3, :3] @ X0[:3, :3]
        plate = np.einsum("nai,nkilj,nbj->nkalb", R_C_S, cov_S.reshape(n, self.K, 3, self.K, 3), R_C_S)
        cov = J @ cov_C @ np.swapaxes(J, 1, 2) + plate.reshape(n, 3 * self.K, 3 * self.K)
        # whitening W with W^T W = inv(cov): W = inv(L) for cov = L L^T
        self.W = np.linalg.inv(np.linalg.cholesky(cov))
        self.info = np.swapaxes(self.W, 1, 2) @ self.W

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        dX = make_transform(Rotation.from_rotvec(x[:3]).as_matrix(), x[3:6])
        return self.X0 @ dX, x[6:].reshape(self.K, 3)

    def start(self) -> np.ndarray:
        """Parameters at ``X0`` with the points m that the weights put best for it (linear least squares)."""
        q = _points_C(self.T_C_T, self.X0, self.pts_S).reshape(len(self.T_C_T), -1)
        m0 = np.linalg.solve(self.info.sum(axis=0), np.einsum("nij,nj->i", self.info, q))
        return np.concatenate([np.zeros(6), m0])

    def cost(self) -> float:
        """Whitened sum of squares at ``X0`` (with the best points)."""
        f = self(self.start())
        return float(f @ f)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        X, m = self.unpack(x)
        r = (_points_C(self.T_C_T, X, self.pts_S) - m[None]).reshape(len(self.T_C_T), -1)
        return np.einsum("nij,nj->ni", self.W, r).reshape(-1)

    def covariance(self, x: np.ndarray) -> np.ndarray:
        """6x6 covariance of X's local parameters (rotvec rad, translation mm) at ``x``: ``inv(J^T J)`` of
        the whitened problem, scaled up by the residual variance when the data scatter more than the noise
        model says."""
        f0 = self(x)
        steps = np.r_[np.full(3, 1e-6), np.full(len(x) - 3, 1e-4)]
        J = np.empty((len(f0), len(x)))
        for k, h in enumerate(steps):
            e = np.zeros_like(x)
            e[k] = h
            J[:, k] = (self(x + e) - self(x - e)) / (2 * h)
        s2 = float(f0 @ f0) / max(J.shape[0] - J.shape[1], 1)
        try:
            return max(s2, 1.0) * np.linalg.inv(J.T @ J)[:6, :6]
        except np.linalg.LinAlgError:
            return np.full((6, 6), np.inf)


def _refine(T_C_T: np.ndarray, pts_S: np.ndarray, X0: np.ndarray, cov_C: np.ndarray, cov_S: np.ndarray,
            passes: int = 2) -> tuple[_Bundle, np.ndarray]:
    """Maximum-likelihood X: Levenberg-Marquardt on the bundle, the weights re-evaluated at each pass's
    answer. Returns the last bundle and its solution vector (X local 6-vector, then the K points)."""
    bundle = _Bundle(T_C_T, pts_S, X0, cov_C, cov_S)
    for k in range(passes):
        x = least_squares(bundle, bundle.start(), method="lm", x_scale="jac").x
        if k + 1 < passes:
            bundle = _Bundle(T_C_T, pts_S, bundle.unpack(x)[0], cov_C, cov_S)
    return bundle, x


def _translation_first(covariance: np.ndarray) -> np.ndarray:
    """The refinement's covariance (rotation vector, translation) in the project's order (translation, rotation)."""
    order = [3, 4, 5, 0, 1, 2]
    return np.asarray(covariance, float)[np.ix_(order, order)]


def _plate_side_covariance(
    pts_S: np.ndarray, plate_covariances: np.ndarray | None, point_covariances: np.ndarray | None,
    sigma_mm: float,
) -> np.ndarray:
    """(N, 3K, 3K) covariance of each pose's plate points in frame S (mm^2).

    From the plate poses' 6x6 (a rigid motion of the points: ``dp = dt + dtheta x p``), or the points' own
    3x3 blocks, or else isotropic ``sigma_mm``; a 0.1 um floor keeps the rigid-only case invertible.
    """
    n, K = pts_S.shape[:2]
    if plate_covariances is None and point_covariances is None:
        return np.broadcast_to(sigma_mm**2 * np.eye(3 * K), (n, 3 * K, 3 * K)).copy()
    cov = np.broadcast_to(1e-8 * np.eye(3 * K), (n, 3 * K, 3 * K)).copy()
    if point_covariances is not None:
        for k in range(K):
            cov[:, 3 * k : 3 * k + 3, 3 * k : 3 * k + 3] += point_covariances[:, k]
    if plate_covariances is not None:
        Jp = np.zeros((n, K, 3, 6))
        Jp[..., :3] = np.eye(3)
        Jp[..., 3:] = -skew(pts_S)
        Jp = Jp.reshape(n, 3 * K, 6)
        cov += Jp @ plate_covariances @ np.swapaxes(Jp, 1, 2)
    return cov


# ---------------------------------------------------------------- the public solver


def pair_residuals(A: np.ndarray, B: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pair: (rotation residual deg, translation residual mm) of ``A X`` against ``X B``."""
    L = A @ X
    Rr = X @ B
    D = np.einsum("nji,njk->nik", L[:, :3, :3], Rr[:, :3, :3])
    ang = np.degrees(np.linalg.norm(Rotation.from_matrix(D).as_rotvec(), axis=1))
    return ang, np.linalg.norm(L[:, :3, 3] - Rr[:, :3, 3], axis=1)


def solve_hand_eye(
    target_poses: ArrayLike,
    plate_poses: ArrayLike,
    method: Method = "refine",
    *,
    plate_points_P: ArrayLike | None = None,
    plate_points_S: ArrayLike | None = None,
    min_pair_rotation_deg: float = 5.0,
    min_axis_spread_deg: float = 3.0,
    tracker_covariances: ArrayLike | None = None,
    tracker_sigma: tuple[float, float] = DEFAULT_TRACKER_SIGMA,
    plate_sigma_mm: float = 0.005,
    plate_covariances: ArrayLike | None = None,
    plate_point_covariances: ArrayLike | None = None,
) -> HandEyeResult:
    """Solve ``A X = X B`` for ``X = T_T_S`` (4x4, mm).

    ``target_poses[i]`` is ``T_C_T`` (the tracker's reading of the target) and ``plate_poses[i]`` is ``T_S_P`` at
    arm pose i (N >= 3).
    ``plate_points_P`` (K, 3 mm, frame P) are the points the refinement and the point residuals use
    (for example the sphere centres); default a plate-sized tetrahedron. ``plate_points_S`` (N, K, 3 mm),
    when given, are those points as measured in each scan (the fitted sphere centres): the refinement then
    uses them instead of ``T_S_P[i] plate_points_P``, which carry only the plate pose's 6 DoF. Pairs whose
    relative rotation is below ``min_pair_rotation_deg`` are dropped; :class:`HandEyeError` is raised when
    fewer than two remain or when all rotations share one axis.

    Noise model of the refinement and the covariance: ``tracker_covariances`` (N, 6, 6) of each reading as
    the tracker driver gives them (``TrackerReading.covariance``: translation mm then rotation vector rad,
    in the camera frame C); without them ``tracker_sigma`` = (mm, rad) per axis for every reading. Plate
    side, one of: ``plate_covariances`` (N, 6, 6), the covariance of each ``T_S_P`` as
    :attr:`PlateFit.covariance` gives it (translation mm, rotation rad, left perturbation in frame S);
    ``plate_point_covariances`` (N, K, 3, 3 mm^2, frame S) of the measured ``plate_points_S``
    (:attr:`SphereFit.centre_covariance`); or else ``plate_sigma_mm``, the 1-sigma per axis of a plate point.

    Twelve parameters: the two pose series and the method, then keyword-only options with defaults: the points the
    refinement uses, the pair selection, and the noise model (per reading or one sigma, three forms on the plate
    side).
    """
    if method not in METHODS:
        raise HandEyeError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    T_C_T = _as_poses(target_poses, "target_poses")
    T_S_P = _as_poses(plate_poses, "plate_poses")
    n = len(T_C_T)
    if n != len(T_S_P):
        raise HandEyeError(f"{n} target poses but {len(T_S_P)} plate poses")
    if n < 3:
        raise HandEyeError(f"hand-eye calibration needs at least 3 poses, got {n}")
    pts_P = DEFAULT_PLATE_POINTS_P if plate_points_P is None else np.asarray(plate_points_P, dtype=float)
    if pts_P.ndim != 2 or pts_P.shape[1] != 3 or len(pts_P) < 3:
        raise HandEyeError(f"plate_points_P must be (K >= 3, 3), got {pts_P.shape}")
    K = len(pts_P)
    pairs, A, B, rejected = _relative_motions(T_C_T, T_S_P, np.radians(min_pair_rotation_deg))
    _check_conditioning(A, min_axis_spread_deg)
    if plate_points_S is None:
        pts_S = np.einsum("nij,kj->nki", T_S_P[:, :3, :3], pts_P) + T_S_P[:, None, :3, 3]
    else:
        pts_S = _as_array(plate_points_S, "plate_points_S", (n, K, 3))
    if tracker_covariances is None:
        cov_C = np.broadcast_to(np.diag(np.repeat(np.square(tracker_sigma), 3)), (n, 6, 6))
    else:
        cov_C = _as_array(tracker_covariances, "tracker_covariances", (n, 6, 6))
    cov_pose = None if plate_covariances is None else _as_array(plate_covariances, "plate_covariances", (n, 6, 6))
    cov_pts = None
    if plate_point_covariances is not None:
        if plate_points_S is None or cov_pose is not None:
            raise HandEyeError("plate_point_covariances go with plate_points_S and without plate_covariances")
        cov_pts = _as_array(plate_point_covariances, "plate_point_covariances", (n, K, 3, 3))
    cov_S = _plate_side_covariance(pts_S, cov_pose, cov_pts, plate_sigma_mm)

    if method == "refine":
        starts = []
        for name, solver in _SOLVERS.items():
            try:
                starts.append((_Bundle(T_C_T, pts_S, solver(A, B), cov_C, cov_S), name))
            except (HandEyeError, np.linalg.LinAlgError) as e:
                log.info("hand-eye start %s failed: %s", name, e)
        if not starts:
            raise HandEyeError("no closed-form solver gave a start for the refinement: data degenerate or too noisy")
        first, name = min(starts, key=lambda b: b[0].cost())
        log.debug("hand-eye refinement starts from %s", name)
        bundle, x = _refine(T_C_T, pts_S, first.X0, cov_C, cov_S)
    else:
        bundle = _Bundle(T_C_T, pts_S, _SOLVERS[method](A, B), cov_C, cov_S)
        x = bundle.start()
    X, m = bundle.unpack(x)
    cov = _translation_first(bundle.covariance(x))
    p = _points_C(T_C_T, X, pts_S)
    point_res = np.sqrt(np.mean(np.sum((p - m[None]) ** 2, axis=2), axis=1))
    T_C_P = _rigid_fit(pts_P, m)
    rot_res, trans_res = pair_residuals(A, B, X)
    log.info(
        "hand-eye %s: %d pairs (%d dropped), point RMS %.4f mm", method, len(pairs), rejected,
        float(np.sqrt(np.mean(point_res**2))),
    )
    return HandEyeResult(
        T_T_S=X,
        method=method,
        pairs=pairs,
        rot_residuals_deg=rot_res,
        trans_residuals_mm=trans_res,
        point_residuals_mm=point_res,
        T_C_P=T_C_P,
        covariance=cov,
        rejected_pairs=rejected,
    )


def _as_array(values: ArrayLike, name: str, shape: tuple[int, ...]) -> np.ndarray:
    """Float array of exactly ``shape``, finite, else :class:`HandEyeError` naming ``name``."""
    a = np.asarray(values, dtype=float)
    if a.shape != shape:
        raise HandEyeError(f"{name} must be {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise HandEyeError(f"{name} contains NaN or inf")
    return a


def _rigid_fit(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares rigid transform mapping ``src`` points onto ``dst`` (Kabsch)."""
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    R = _procrustes((src - cs).T @ (dst - cd))
    return make_transform(R, cd - R @ cs)


__all__ = ["METHODS", "HandEyeError", "HandEyeResult", "pair_residuals", "solve_hand_eye"]
