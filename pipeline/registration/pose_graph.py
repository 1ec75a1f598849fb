"""The global pose graph over all scans of a job (docs/registration.md, "Pose graph").

Every scan ``i`` has a tracker pose ``P_i = T_W_S_i`` (prior) with a 6x6 covariance; every
corrected overlap gives a relative-pose edge. Scans are grouped by tracker station; a coordinate transfer
gives the whole next station an error on top of the previous station's, so station ``k`` carries the
product of the transfer errors ``1..k`` (each a ``TransferPrior``: a world motion about the still target's
origin, with the two readings' covariance); edges between stations pull back that accumulated drift while
the priors keep every scan near its tracker reading. The solution minimises the sum of squared, whitened
residuals (scipy least squares with a sparse Jacobian). With a ``mounts.MountPrior`` the shared
scanner-mount correction is one more unknown (see ``mounts``).

Conventions: a pose perturbation is ``(t mm, rotation vector rad)`` of a world-frame motion about a stated
centre (the scan origin for priors, the overlap centre for edges, the station's scans' centroid for station
corrections); covariances use the same order (translation first).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation
from tandemscan.pipeline.geometry.frames import invert
from tandemscan.pipeline.registration.icp import RefineError
from tandemscan.pipeline.registration.mounts import MountEstimate, MountPrior, MountSolve, schur

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ScanPrior:
    """A scan's tracker pose ``T_W_S`` (4x4 mm), its covariance (6x6, t mm^2 then r rad^2, about the scan
    origin, world axes) and the tracker station it was measured from."""

    T_W_S: np.ndarray
    covariance: np.ndarray
    station: int = 0


@dataclass(frozen=True)
class TransferPrior:
    """The error a coordinate transfer gives tracker station ``station`` (and, composed, every later one): a
    world motion about ``centre_mm`` (the still target's origin in W) with ``covariance`` (6x6, t mm^2 of that
    point, then r rad^2; world axes), see ``uncertainty.transfer_covariance``."""

    station: int
    centre_mm: np.ndarray
    covariance: np.ndarray


@dataclass(frozen=True)
class PairEdge:
    """A relative-pose measurement between scans ``i`` (fixed) and ``j`` (moved).

    ``correction`` is the world-frame 4x4 that moved scan ``j``, placed at its prior pose, onto scan ``i`` at
    its prior pose; ``information`` is 6x6 (t, r) about ``centre_mm`` (the overlap's centre, world).
    """

    i: int
    j: int
    correction: np.ndarray
    information: np.ndarray
    centre_mm: np.ndarray


def _about(centre: np.ndarray, T: np.ndarray) -> np.ndarray:
    """``Tr(-c) T Tr(c)``: the same motion written about ``centre``. Works on stacks."""
    out = np.array(T, dtype=float)
    R = out[..., :3, :3]
    out[..., :3, 3] = out[..., :3, 3] + np.einsum("...ij,...j->...i", R, centre) - centre
    return out


def _exp(x: np.ndarray) -> np.ndarray:
    """Stack of 4x4 from ``(n, 6)`` (t, rotvec)."""
    T = np.tile(np.eye(4), (len(x), 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(x[:, 3:]).as_matrix()
    T[:, :3, 3] = x[:, :3]
    return T


def _log(T: np.ndarray) -> np.ndarray:
    """``(n, 6)`` (t, rotvec) of a stack of 4x4."""
    return np.c_[T[:, :3, 3], Rotation.from_matrix(T[:, :3, :3]).as_rotvec()]


def _whitener(matrix: np.ndarray, inverse: bool, what: str) -> np.ndarray:
    """``W`` with ``W^T W`` = the information (``inverse``: of a covariance, which must be positive
    definite; an information matrix may be singular in directions it does not constrain)."""
    M = np.asarray(matrix, float)
    if M.shape != (6, 6) or not np.all(np.isfinite(M)):
        raise RefineError(f"{what}: expected a finite 6x6 matrix, got shape {M.shape}")
    if inverse:
        try:
            return np.linalg.cholesky(np.linalg.inv(0.5 * (M + M.T))).T
        except np.linalg.LinAlgError as e:
            raise RefineError(f"{what}: not positive definite") from e
    w, V = np.linalg.eigh(0.5 * (M + M.T))
    if w.min() < -1e-9 * max(w.max(), 1e-300):
        raise RefineError(f"{what}: not positive semi-definite")
    return np.sqrt(np.clip(w, 0.0, None))[:, None] * V.T


def constrained_edge(
    correction: ArrayLike, information: ArrayLike, centre_mm: ArrayLike, length_mm: float, min_ratio: float
) -> tuple[np.ndarray, np.ndarray]:
    """Keep only what an overlap really measures (degeneracy-aware edge).

    A smooth overlap (plane, cylinder, extrusion) leaves directions in which the registration slides
    freely. With rotations scaled by ``length_mm`` (the overlap's size) so that both kinds of direction
    compare, the eigen-directions of ``information`` weaker than ``min_ratio`` of the strongest are dropped:
    the correction is projected onto the rest and the information there is zero. Returns
    ``(correction, information)``.
    """
    c = np.asarray(centre_mm, float)
    S = np.diag([1.0, 1.0, 1.0, 1.0 / length_mm, 1.0 / length_mm, 1.0 / length_mm])
    info_s = S @ np.asarray(information, float) @ S          # information in (mm, mm-at-length) units
    w, V = np.linalg.eigh(0.5 * (info_s + info_s.T))
    keep = w >= min_ratio * w.max()
    P = V[:, keep] @ V[:, keep].T
    e = S @ P @ np.linalg.solve(S, _log(_about(c, np.asarray(correction, float)[None]))[0])
    info = np.linalg.inv(S) @ (V[:, keep] * w[keep]) @ V[:, keep].T @ np.linalg.inv(S)
    return _about(-c, _exp(e[None]))[0], info


@dataclass(frozen=True)
class RefineResult:
    """Refined ``T_W_S`` per scan, the per-station world corrections, residual figures, and the shared
    mount correction when one was estimated."""

    poses: list[np.ndarray]
    station_corrections: dict[int, np.ndarray]
    cost_before: float
    cost_after: float
    success: bool
    mount: MountEstimate | None = None


def refine_poses(
    scans: Sequence[ScanPrior],
    edges: Sequence[PairEdge],
    transfers: Sequence[TransferPrior] = (),
    mount_prior: MountPrior | None = None,
) -> RefineResult:
    """Solve the pose graph; returns refined ``T_W_S`` for every scan.

    ``transfers``: the prior of each coordinate transfer, one for every station after the first (a station
    without scans may have one too: its drift still reaches the later ones); stations are numbered in transfer
    order and the first defines the world. Without them only per-scan corrections are solved. With ``mount_prior`` one
    shared scanner-mount correction ``D`` (``T_W_S_i -> T_W_S_i D``) is solved as well: first in all six
    directions, then, if the overlaps leave some unobserved, again with those held at the prior.
    """
    n = len(scans)
    if n == 0:
        return RefineResult([], {}, 0.0, 0.0, True)
    graph = _Graph(scans, edges, transfers)
    if mount_prior is None:
        sol, x0 = graph.solve(None)
        return graph.result(sol, x0, None)
    prior = np.asarray(mount_prior.covariance, float)
    _whitener(prior, True, "mount prior covariance")
    L = np.linalg.cholesky(0.5 * (prior + prior.T))            # D = L u, u ~ N(0, I) a priori
    sol, x0 = graph.solve(L)                                    # all six directions
    data_u = schur(graph.data_jacobian(sol.jac, 6), graph.n_blocks)   # data information on u
    ratio, U = np.linalg.eigh(0.5 * (data_u + data_u.T))
    observed = ratio >= mount_prior.min_information_ratio
    basis = np.eye(6)                                           # directions of u estimated (orthonormal)
    if not observed.all():
        basis = U[:, observed]
        sol, x0 = graph.solve(L @ basis if observed.any() else None)
    Linv = np.linalg.inv(L)
    return graph.result(sol, x0, MountSolve(L, basis, ratio, U, Linv.T @ data_u @ Linv, prior))


class _Graph:
    """The pose graph's residuals (see :func:`refine_poses`). Unknowns: a 6-vector per scan, one per movable
    station, then optionally ``k`` coefficients ``z`` of the shared mount correction ``D = B z`` (``B`` 6 x k,
    chosen per solve as ``L`` times orthonormal columns, so that the whitened prior is ``z`` itself)."""

    def __init__(self, scans: Sequence[ScanPrior], edges: Sequence[PairEdge], transfers: Sequence[TransferPrior]
                 ) -> None:
        n = self.n = len(scans)
        self.P = np.stack([np.asarray(s.T_W_S, float) for s in scans])
        self.origins = self.P[:, :3, 3]
        self.Wp = np.stack([_whitener(s.covariance, True, f"scan {i} covariance") for i, s in enumerate(scans)])
        stations = sorted({s.station for s in scans})
        by_station = {t.station: t for t in transfers}
        if transfers and (len(by_station) != len(transfers) or min(by_station) <= stations[0]
                          or not set(stations[1:]) <= set(by_station)):
            raise RefineError(f"transfer priors for stations {[t.station for t in transfers]}: need one for each "
                              f"station after the first of {stations}, or none")
        self.movable = sorted(by_station)
        self.col = {k: n + m for m, k in enumerate(self.movable)}
        self.n_blocks = 6 * (n + len(self.movable))
        self.sid = np.array([s.station for s in scans])
        self.centres = {k: np.asarray(by_station[k].centre_mm, float) for k in self.movable}
        self.Wt = {k: _whitener(by_station[k].covariance, True, f"transfer {k} covariance") for k in self.movable}
        for e in edges:
            if not (0 <= e.i < n and 0 <= e.j < n) or e.i == e.j:
                raise RefineError(f"edge ({e.i}, {e.j}) does not join two different scans of {n}")
        self.ei = np.array([e.i for e in edges], dtype=int)
        self.ej = np.array([e.j for e in edges], dtype=int)
        # relative measurement Z_ij = P_i^-1 C P_j, and edge whiteners
        P = self.P
        self.Z = np.stack([invert(P[e.i]) @ e.correction @ P[e.j] for e in edges]) if edges else np.zeros((0, 4, 4))
        self.We = np.stack([_whitener(e.information, False, f"edge ({e.i}, {e.j})") for e in edges]) if edges else None
        self.ec = np.stack([np.asarray(e.centre_mm, float) for e in edges]) if edges else np.zeros((0, 3))
        self.B: np.ndarray | None = None

    def station_corrections(self, X: np.ndarray) -> dict[int, np.ndarray]:
        A, out = np.eye(4), {}
        for k in self.movable:                      # transfer k on top of all earlier ones
            A = _about(-self.centres[k], _exp(X[self.col[k]][None]))[0] @ A
            out[k] = A
        return out

    def mount(self, x: np.ndarray) -> np.ndarray:
        """The 6-vector of ``D`` (t mm, rotvec rad) at ``x`` (zero without a mount unknown)."""
        return np.zeros(6) if self.B is None else self.B @ x[self.n_blocks:]

    def poses(self, x: np.ndarray) -> np.ndarray:
        X = x[:self.n_blocks].reshape(-1, 6)
        Pm = self.P @ _exp(self.mount(x)[None])[0]                  # the shared mount: P_i D
        out = _about(-self.origins, _exp(X[:self.n])) @ Pm          # Tr(o) Exp(d) Tr(-o) P D
        for k, A in self.station_corrections(X).items():
            out[self.sid == k] = A @ out[self.sid == k]
        return out

    def residuals(self, x: np.ndarray) -> np.ndarray:
        X = x[:self.n_blocks].reshape(-1, 6)
        r = [np.einsum("nij,nj->ni", self.Wp, X[:self.n]).ravel()]
        r += [self.Wt[k] @ X[self.col[k]] for k in self.movable]
        if len(self.ei):
            Xp = self.poses(x)
            E = Xp[self.ei] @ self.Z @ np.linalg.inv(Xp[self.ej])
            r.append(np.einsum("nij,nj->ni", self.We, _log(_about(self.ec, E))).ravel())
        r.append(x[self.n_blocks:])                                 # the mount prior, whitened
        return np.concatenate(r)

    def data_jacobian(self, jac, k: int) -> np.ndarray:
        """Dense Jacobian without the mount prior's ``k`` rows (the last ones)."""
        J = jac.toarray() if hasattr(jac, "toarray") else np.asarray(jac)
        return J[:-k] if k else J

    def solve(self, B: np.ndarray | None):
        """Least squares with the mount correction ``D = B z`` (None: no mount unknown)."""
        self.B = B
        n, k = self.n, 0 if B is None else B.shape[1]
        rows_edges = 6 * n + 6 * len(self.movable)
        sparsity = lil_matrix((rows_edges + 6 * len(self.ei) + k, self.n_blocks + k), dtype=int)
        for i in range(n):
            sparsity[6 * i:6 * i + 6, 6 * i:6 * i + 6] = 1
        for m, c in enumerate(self.col[s] for s in self.movable):
            sparsity[6 * n + 6 * m:6 * n + 6 * m + 6, 6 * c:6 * c + 6] = 1
        row = rows_edges
        for a, b in zip(self.ei, self.ej, strict=True):
            for s in (a, b):
                sparsity[row:row + 6, 6 * s:6 * s + 6] = 1
                for c in [self.col[q] for q in self.movable if q <= self.sid[s]]:
                    sparsity[row:row + 6, 6 * c:6 * c + 6] = 1
            sparsity[row:row + 6, self.n_blocks:] = 1               # every edge sees the mount
            row += 6
        for m in range(k):
            sparsity[row + m, self.n_blocks + m] = 1
        x0 = np.zeros(self.n_blocks + k)
        sol = least_squares(self.residuals, x0, jac_sparsity=sparsity, method="trf", x_scale="jac",
                            xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=200)
        return sol, x0

    def result(self, sol, x0: np.ndarray, mount: MountSolve | None) -> RefineResult:
        cost0 = 0.5 * float(np.sum(self.residuals(x0) ** 2))
        out = self.poses(sol.x)
        corr = self.station_corrections(sol.x[:self.n_blocks].reshape(-1, 6))
        estimate = None
        if mount is not None:
            k = mount.basis.shape[1] if self.B is not None else 0
            # posterior: what was estimated from the solution's Jacobian, the rest keeps the prior's variance
            cov_u = np.eye(6)
            if k:
                J = self.data_jacobian(sol.jac, 0)
                cov_z = np.linalg.inv(J.T @ J)[self.n_blocks:, self.n_blocks:]
                cov_u = mount.basis @ cov_z @ mount.basis.T + cov_u - mount.basis @ mount.basis.T
            cov = mount.L @ cov_u @ mount.L.T
            d = self.mount(sol.x)
            estimate = MountEstimate(_exp(d[None])[0], 0.5 * (cov + cov.T), mount.prior,
                                     0.5 * (mount.data_information + mount.data_information.T), mount.ratio,
                                     mount.directions, k)
            log.info("pose graph: mount correction %s mm, %s deg (%d of 6 directions observed)",
                     np.round(d[:3], 4), np.round(np.degrees(d[3:]), 5), k)
        log.info("pose graph: %d scans, %d edges, %d transfers; cost %.3g -> %.3g", self.n, len(self.ei),
                 len(self.movable), cost0, sol.cost)
        return RefineResult([T for T in out], corr, cost0, float(sol.cost), bool(sol.success), estimate)
