"""The global pose graph over all scans of a job (docs/registration.md, "Pose graph").

Every scan ``i`` has a tracker pose ``P_i = T_W_S_i`` (prior) with a 6x6 covariance; every
corrected overlap gives a relative-pose edge. Scans are grouped by tracker station; a coordinate transfer
gives the whole next station an error on top of the previous station's, so station ``k`` carries the
product of the transfer errors ``1..k`` (each a ``TransferPrior``: a world motion about the still target's
origin, with the two readings' covariance); edges between stations pull back that accumulated drift while
the priors keep every scan near its tracker reading. The solution minimises the sum of squared, whitened
residuals by Gauss-Newton on the exact residuals with their first-order sparse Jacobian (every correction is a
small world motion, so the Jacobian hardly depends on the estimate: :meth:`_Graph.jacobian`), each step a
sparse LU solve of the normal equations (scipy.sparse), halved while it does not lower the cost. With a
``mount_unknown.MountPrior`` the shared scanner-mount correction is one more unknown (see ``mount_unknown``).

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
from scipy import sparse
from scipy.sparse.linalg import splu
from scipy.spatial.transform import Rotation
from tandemscan.pipeline.geometry.frames import invert
from tandemscan.pipeline.geometry.uncertainty import skew
from tandemscan.pipeline.registration.icp import RefineError
from tandemscan.pipeline.registration.mount_unknown import MountEstimate, MountPrior, MountSolve, schur

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


@dataclass(frozen=True)
class _Solution:
    """A solved graph: the unknowns, the Jacobian (sparse, :meth:`_Graph.jacobian`), half the sum of squared
    residuals, and whether the steps converged."""

    x: np.ndarray
    jac: sparse.csr_matrix
    cost: float
    success: bool


def _motion_about(offset: np.ndarray) -> np.ndarray:
    """``M(o) = [[I, [o]x], [0, I]]`` for (m, 3) offsets ``o``: a small motion (t, r) about a point ``o``
    (relative to the reference point) as the same motion about the reference point."""
    o = np.atleast_2d(offset)
    M = np.tile(np.eye(6), (len(o), 1, 1))
    M[:, 0, 4], M[:, 0, 5] = -o[:, 2], o[:, 1]
    M[:, 1, 3], M[:, 1, 5] = o[:, 2], -o[:, 0]
    M[:, 2, 3], M[:, 2, 4] = -o[:, 1], o[:, 0]
    return M


def _inverse_left_jacobian(phi: np.ndarray) -> np.ndarray:
    """(m, 3, 3) inverse left Jacobians of SO(3) at rotation vectors ``phi`` (m, 3): a small rotation ``d``
    applied on the left of ``Exp(phi)`` changes its rotation vector by ``Jl^-1(phi) d``."""
    theta = np.linalg.norm(phi, axis=1)
    K = skew(phi)
    small = theta < 1e-4
    half = np.where(small, 1.0, 0.5 * theta)
    coef = np.where(small, 1.0 / 12.0, (1.0 - half / np.tan(half)) / np.where(small, 1.0, theta) ** 2)
    return np.eye(3) - 0.5 * K + coef[:, None, None] * (K @ K)


def _adjoint(P: np.ndarray) -> np.ndarray:
    """``Ad(P) = [[R, [t]x R], [0, R]]`` of a stack of poses: a small motion in the pose's own frame (right
    perturbation) as a world motion about the world origin."""
    R = P[:, :3, :3]
    A = np.zeros((len(P), 6, 6))
    A[:, :3, :3] = A[:, 3:, 3:] = R
    A[:, :3, 3:] = skew(P[:, :3, 3]) @ R
    return A


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

    def jacobian(self, x: np.ndarray) -> sparse.csr_matrix:
        """The residuals' Jacobian at ``x`` (sparse; rows as :meth:`residuals`), to first order in the
        corrections ``x`` themselves (each a small world motion) and exact in the edges' corrections.

        Unknowns as world motions about the world origin: a scan's ``M(o) x`` (about its origin ``o``,
        ``M(o) = [[I, [o]x], [0, I]]``), a transfer's ``M(c) y`` (about the still target ``c``), the mount's
        ``Ad(Xp) D`` (a right perturbation of the pose ``Xp``, ``Ad(Xp) = [[R, [t]x R], [0, R]]``). An edge
        residual ``We log(about(c_e, E))``, ``E = Xp_i Z Xp_j^-1`` (about ``c_e``: rotation ``R_0`` with rotation
        vector ``phi``, translation ``t_0``), moves by ``We L (M(-c_e) xi_i - Ad(E) M(-c_e) xi_j)`` with
        ``L = [[I, -[t_0]x], [0, Jl^-1(phi)]]`` (the rotation vector's inverse left Jacobian), where ``xi`` is
        the sum of the motions of a scan's pose: a mount moves both scans of an edge nearly alike, so these
        terms are what an edge measures of it."""
        n, k = self.n, 0 if self.B is None else self.B.shape[1]
        rows, cols, vals = [], [], []

        def put(row0: np.ndarray, col0: np.ndarray, blocks: np.ndarray) -> None:
            """(m, 6, c) blocks at rows ``row0 + 0..5`` and columns ``col0 + 0..c-1``."""
            c = blocks.shape[2]
            rows.append(np.repeat(row0[:, None] + np.arange(6), c, axis=1).ravel())
            cols.append(np.tile(col0[:, None] + np.arange(c), (1, 6)).ravel())
            vals.append(blocks.reshape(len(row0), -1).ravel())

        put(6 * np.arange(n), 6 * np.arange(n), self.Wp)
        for m, q in enumerate(self.movable):
            put(np.array([6 * (n + m)]), np.array([6 * self.col[q]]), self.Wt[q][None])
        n_rows = 6 * (n + len(self.movable)) + 6 * len(self.ei)
        row0 = 6 * (n + len(self.movable)) + 6 * np.arange(len(self.ei))
        if len(self.ei):
            Xp = self.poses(x)
            E = _about(self.ec, Xp[self.ei] @ self.Z @ invert(Xp[self.ej]))       # about c_e
            L = np.tile(np.eye(6), (len(E), 1, 1))
            L[:, :3, 3:] = -skew(E[:, :3, 3])
            L[:, 3:, 3:] = _inverse_left_jacobian(_log(E)[:, 3:])
            to_edge = self.We @ L @ _motion_about(-self.ec)
            side_i, side_j = to_edge, -self.We @ L @ _adjoint(E) @ _motion_about(-self.ec)
            for side, rows_of in ((self.ei, side_i), (self.ej, side_j)):
                put(row0, 6 * side, rows_of @ _motion_about(self.origins[side]))
            for q in self.movable:
                on_i, on_j = self.sid[self.ei] >= q, self.sid[self.ej] >= q
                hit = on_i | on_j
                if hit.any():
                    M = _motion_about(self.centres[q])
                    blocks = on_i[hit, None, None] * side_i[hit] @ M + on_j[hit, None, None] * side_j[hit] @ M
                    put(row0[hit], np.full(hit.sum(), 6 * self.col[q]), blocks)
            if k:
                Ad = _adjoint(Xp)
                put(row0, np.full(len(self.ei), self.n_blocks), (side_i @ Ad[self.ei] + side_j @ Ad[self.ej]) @ self.B)
        J = sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                              shape=(n_rows, self.n_blocks + k))
        if k:
            J = sparse.vstack([J, sparse.hstack([sparse.csr_matrix((k, self.n_blocks)), sparse.identity(k)])])
        return J.tocsr()

    def solve(self, B: np.ndarray | None, max_steps: int = 50, tolerance: float = 1e-12
              ) -> tuple[_Solution, np.ndarray]:
        """Least squares with the mount correction ``D = B z`` (None: no mount unknown): Gauss-Newton steps with
        :meth:`jacobian` at the current estimate, each halved while it does not lower the cost, until a step
        lowers the cost by less than ``tolerance`` of it."""
        self.B = B
        x0 = np.zeros(self.n_blocks + (0 if B is None else B.shape[1]))
        x, r = x0, self.residuals(x0)
        cost, success = 0.5 * float(r @ r), False
        for _ in range(max_steps):
            J = self.jacobian(x)
            step = splu((J.T @ J).tocsc()).solve(-(J.T @ r))
            for _halving in range(30):
                r_new = self.residuals(x + step)
                cost_new = 0.5 * float(r_new @ r_new)
                if cost_new <= cost:
                    break
                step = 0.5 * step
            else:                                   # no step lowers the cost: converged as far as it can
                success = True
                break
            x, r, decrease, cost = x + step, r_new, cost - cost_new, cost_new
            if decrease <= tolerance * max(cost, 1e-300):
                success = True
                break
        return _Solution(x, self.jacobian(x), cost, success), x0

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
