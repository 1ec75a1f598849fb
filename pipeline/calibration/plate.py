"""Calibration plate: find the three reference spheres in a scan and build the plate frame (Eq. 7-8).

The plate carries three spheres A, X, Y of one calibrated diameter. Plate frame ``P``: x along A->X, origin
at the foot of the perpendicular from Y onto the line A-X, y from there towards Y, z = x cross y. The
result is ``T_S_P`` (plate into scanner frame S, mm) with the residuals that show how far to trust it.

Segmentation is a Hough vote: every surface point, moved by one radius against its normal (oriented towards
the scanner at the S origin), votes for a sphere centre; votes of points on a sphere of the nominal radius
pile up, votes of flat or differently curved surfaces spread out. Each vote peak is then fitted: algebraic
sphere (start), RANSAC against outliers (stem, plate, mixed pixels), geometric least squares (refinement).
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import least_squares
from scipy.spatial import cKDTree
from tandemscan.config.models import CalibrationConfig
from tandemscan.pipeline.geometry.frames import make_transform

log = logging.getLogger(__name__)

SPHERE_NAMES = ("A", "X", "Y")


class PlateError(ValueError):
    """The plate scan does not show the three spheres as configured; the message says which and why."""


@dataclass(frozen=True)
class SphereFit:
    """One fitted sphere in the scan frame (mm)."""

    centre: np.ndarray
    radius_mm: float
    free_radius_mm: float
    rms_mm: float
    n_points: int
    n_inliers: int
    centre_sigma_mm: float
    #: 3x3 covariance of ``centre`` (mm^2, frame S) from the fit's Jacobian: a cap seen from one side is
    #: pinned better along the view than across it
    centre_covariance: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))


@dataclass(frozen=True)
class PlateFit:
    """The plate seen from the scanner: ``T_S_P`` (mm) and its residuals.

    ``layout_residuals_mm`` holds measured minus nominal centre-to-centre distances (AX, AY, XY);
    ``spheres`` the fits by name; ``covariance`` the 6x6 of ``T_S_P`` propagated from the centre fits
    (translation mm then rotation vector rad, a perturbation applied on the left, in frame S).
    """

    T_S_P: np.ndarray
    spheres: dict[str, SphereFit]
    layout_residuals_mm: dict[str, float] = field(default_factory=dict)
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))

    @property
    def centres_S(self) -> np.ndarray:
        """(3, 3) sphere centres A, X, Y in the scanner frame (mm)."""
        return np.stack([self.spheres[n].centre for n in SPHERE_NAMES])

    @property
    def centre_covariances(self) -> np.ndarray:
        """(3, 3, 3) covariances of the centres A, X, Y (mm^2, frame S)."""
        return np.stack([self.spheres[n].centre_covariance for n in SPHERE_NAMES])

    @property
    def centre_sigma_mm(self) -> float:
        """Largest 1-sigma centre uncertainty of the three fits (mm)."""
        return max(s.centre_sigma_mm for s in self.spheres.values())


# ---------------------------------------------------------------- plate geometry


def nominal_centres_P(cfg: CalibrationConfig) -> np.ndarray:
    """(3, 3) nominal centres of A, X, Y in the plate frame (mm)."""
    return np.array([cfg.centre_A_mm, cfg.centre_X_mm, cfg.centre_Y_mm], dtype=float)


def plate_frame(a: ArrayLike, x: ArrayLike, y: ArrayLike) -> np.ndarray:
    """Eq. 7-8: ``T_S_P`` from the centres of A, X and Y given in frame S (mm)."""
    a, x, y = (np.asarray(v, dtype=float) for v in (a, x, y))
    ex = x - a
    n = np.linalg.norm(ex)
    if n < 1e-6:
        raise PlateError("spheres A and X coincide: no plate x axis")
    ex /= n
    origin = a + np.dot(y - a, ex) * ex
    ey = y - origin
    m = np.linalg.norm(ey)
    if m < 1e-6:
        raise PlateError("sphere Y lies on the line A-X: no plate y axis")
    ey /= m
    return make_transform(np.column_stack([ex, ey, np.cross(ex, ey)]), origin)


# ---------------------------------------------------------------- sphere fitting


def fit_sphere_algebraic(points: ArrayLike) -> tuple[np.ndarray, float]:
    """Linear least-squares sphere (centre mm, radius mm): ``|p|^2 = 2 c.p + d``; needs >= 4 points."""
    P = np.asarray(points, dtype=float)
    if len(P) < 4:
        raise PlateError(f"a sphere fit needs at least 4 points, got {len(P)}")
    m = P.mean(axis=0)
    Q = P - m
    A = np.column_stack([2.0 * Q, np.ones(len(Q))])
    sol, *_ = np.linalg.lstsq(A, np.einsum("ij,ij->i", Q, Q), rcond=None)
    c = sol[:3]
    r2 = sol[3] + c @ c
    if not np.isfinite(r2) or r2 <= 0:
        raise PlateError("degenerate point set for a sphere fit")
    return c + m, float(np.sqrt(r2))


def _ransac_sphere(
    P: np.ndarray, radius_mm: float, tol_mm: float, rng: np.random.Generator, iterations: int = 300
) -> np.ndarray:
    """Boolean inlier mask of the best 4-point sphere whose radius is near ``radius_mm``."""
    n = len(P)
    S = P[rng.integers(0, n, (iterations, 4))]  # (it, 4, 3); a repeated point makes D singular: skipped
    base = S[:, 0, :]
    D = S[:, 1:, :] - base[:, None, :]  # (it, 3, 3)
    rhs = 0.5 * np.einsum("kij,kij->ki", D, D)
    ok = np.abs(np.linalg.det(D)) > 1e-9 * radius_mm**3
    if not np.any(ok):
        return np.ones(n, dtype=bool)
    c = base[ok] + np.linalg.solve(D[ok], rhs[ok][..., None])[..., 0]
    r = np.linalg.norm(S[ok, 0, :] - c, axis=1)
    plausible = np.abs(r - radius_mm) < 0.25 * radius_mm
    if not np.any(plausible):
        return np.ones(n, dtype=bool)
    c, r = c[plausible], r[plausible]
    dist = np.abs(np.linalg.norm(P[None, :, :] - c[:, None, :], axis=2) - r[:, None])
    counts = (dist < tol_mm).sum(axis=1)
    return dist[int(np.argmax(counts))] < tol_mm


def _geometric_fit(
    P: np.ndarray, centre: np.ndarray, radius_mm: float | None
) -> tuple[np.ndarray, float, np.ndarray]:
    """Orthogonal-distance fit; radius free when ``radius_mm`` is None. Returns (centre, radius, centre
    covariance 3x3 mm^2)."""
    fixed = radius_mm is not None

    def resid(x: np.ndarray) -> np.ndarray:
        r = radius_mm if fixed else x[3]
        return np.linalg.norm(P - x[:3], axis=1) - r

    def jac(x: np.ndarray) -> np.ndarray:
        d = P - x[:3]
        u = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        return -u if fixed else np.column_stack([-u, -np.ones(len(P))])

    x0 = centre if fixed else np.append(centre, np.linalg.norm(P - centre, axis=1).mean())
    sol = least_squares(resid, x0, jac=jac, method="lm")
    J = sol.jac
    dof = max(len(P) - J.shape[1], 1)
    s2 = float(sol.fun @ sol.fun) / dof
    try:
        cov = s2 * np.linalg.inv(J.T @ J)[:3, :3]
    except np.linalg.LinAlgError:
        cov = np.full((3, 3), np.inf)
    r = float(radius_mm) if fixed else float(sol.x[3])
    return sol.x[:3].copy(), r, cov


def fit_sphere(
    points: ArrayLike,
    radius_mm: float,
    *,
    noise_mm: float = 0.05,
    fixed_radius: bool = True,
    rng: np.random.Generator | None = None,
) -> SphereFit:
    """Robust sphere fit on points near one sphere (mm): algebraic start, RANSAC, geometric refinement.

    ``free_radius_mm`` is the radius of the unconstrained fit (for the check against the nominal);
    ``radius_mm``/``centre`` come from the final fit, with the radius held at ``radius_mm`` when
    ``fixed_radius``.
    """
    P = np.asarray(points, dtype=float)
    rng = rng if rng is not None else np.random.default_rng(0)
    if len(P) < 10:
        raise PlateError(f"too few points on the sphere ({len(P)})")
    tol = max(4.0 * noise_mm, 0.1)
    inl = _ransac_sphere(P, radius_mm, tol, rng)
    if inl.sum() < 10:
        raise PlateError("no sphere consensus in the points")
    c, _ = fit_sphere_algebraic(P[inl])
    c, r_free, _ = _geometric_fit(P[inl], c, None)
    # one re-selection pass with the refined model: drop points beyond 4 sigma of its residual
    d = np.abs(np.linalg.norm(P - c, axis=1) - r_free)
    sig = max(1.4826 * float(np.median(d[inl])), 0.25 * noise_mm, 1e-4)
    inl = d < max(4.0 * sig, 3.0 * noise_mm)
    c, r_free, cov = _geometric_fit(P[inl], c, None)
    if fixed_radius:
        c, r, cov = _geometric_fit(P[inl], c, radius_mm)
    else:
        r = r_free
    res = np.linalg.norm(P[inl] - c, axis=1) - r
    return SphereFit(
        centre=c,
        radius_mm=r,
        free_radius_mm=r_free,
        rms_mm=float(np.sqrt(np.mean(res**2))),
        n_points=len(P),
        n_inliers=int(inl.sum()),
        centre_sigma_mm=float(np.sqrt(max(np.max(np.linalg.eigvalsh(cov)), 0.0))) if np.all(np.isfinite(cov))
        else float("inf"),
        centre_covariance=cov,
    )


# ---------------------------------------------------------------- segmentation


def normals_towards_scanner(points: ArrayLike, k: int = 16) -> np.ndarray:
    """Unit normals by local PCA over ``k`` neighbours, oriented towards the scanner origin (frame S)."""
    P = np.asarray(points, dtype=float)
    k = min(k, len(P))
    _, nn = cKDTree(P).query(P, k=k)
    Q = P[nn] - P[nn].mean(axis=1, keepdims=True)
    C = np.einsum("nki,nkj->nij", Q, Q)
    _, vecs = np.linalg.eigh(C)
    n = vecs[:, :, 0]
    flip = np.einsum("ij,ij->i", n, P) > 0
    n[flip] *= -1
    return n


def sphere_candidates(
    points: ArrayLike, radius_mm: float, normals: ArrayLike | None = None, min_votes: int = 30,
    max_candidates: int = 8,
) -> list[np.ndarray]:
    """Centre candidates (mm, frame S) of spheres of ``radius_mm``, strongest first (Hough vote)."""
    P = np.asarray(points, dtype=float)
    N = normals_towards_scanner(P) if normals is None else np.asarray(normals, dtype=float)
    flip = np.einsum("ij,ij->i", N, P) > 0
    N = np.where(flip[:, None], -N, N)
    votes = P - radius_mm * N
    cell = max(radius_mm / 10.0, 0.5)
    keys = np.floor(votes / cell).astype(np.int64)
    keys -= keys.min(axis=0) - 1
    span = keys.max(axis=0) + 2
    codes = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
    uniq, first, counts = np.unique(codes, return_index=True, return_counts=True)
    # sum each cell's count over its 3x3x3 neighbourhood, so a peak split by a cell border still counts
    summed = np.zeros(len(uniq), dtype=np.int64)
    for a, b, c in itertools.product((-1, 0, 1), repeat=3):
        nb = uniq + (a * span[1] + b) * span[2] + c
        pos = np.clip(np.searchsorted(uniq, nb), 0, len(uniq) - 1)
        summed += np.where(uniq[pos] == nb, counts[pos], 0)
    order = np.argsort(-summed)
    threshold = max(min_votes, 0.2 * float(summed[order[0]])) if len(order) else min_votes
    out: list[np.ndarray] = []
    for u in order:
        if summed[u] < threshold or len(out) >= max_candidates:
            break
        cell_centre = votes[first[u]]
        if any(np.linalg.norm(cell_centre - o) <= radius_mm for o in out):
            continue
        near = np.abs(keys - keys[first[u]]).max(axis=1) <= 1
        out.append(np.median(votes[near], axis=0))
    return out


def _match_layout(
    centres: list[np.ndarray], nominal: np.ndarray, tol_mm: float
) -> tuple[dict[str, int], dict[str, float]] | None:
    """Best assignment of fitted centres to names A, X, Y by centre distances; None when none fits."""
    pairs = (("AX", 0, 1), ("AY", 0, 2), ("XY", 1, 2))
    nom = {p: float(np.linalg.norm(nominal[i] - nominal[j])) for p, i, j in pairs}
    best: tuple[float, dict[str, int], dict[str, float]] | None = None
    for perm in itertools.permutations(range(len(centres)), 3):
        res = {p: float(np.linalg.norm(centres[perm[i]] - centres[perm[j]])) - nom[p] for p, i, j in pairs}
        worst = max(abs(v) for v in res.values())
        if worst <= tol_mm and (best is None or worst < best[0]):
            best = (worst, dict(zip(SPHERE_NAMES, perm, strict=True)), res)
    return None if best is None else (best[1], best[2])


def _missing_spheres(centres: list[np.ndarray], nominal: np.ndarray, tol_mm: float) -> str:
    """Name the spheres that could not be found, from the distances between the ones that were."""
    if len(centres) < 2:
        return "spheres not found: " + ", ".join(SPHERE_NAMES) if not centres else "two spheres not found"
    found: set[str] = set()
    for i, j in itertools.combinations(range(len(centres)), 2):
        d = float(np.linalg.norm(centres[i] - centres[j]))
        for a, b in itertools.combinations(range(3), 2):
            if abs(d - np.linalg.norm(nominal[a] - nominal[b])) <= tol_mm:
                found |= {SPHERE_NAMES[a], SPHERE_NAMES[b]}
    missing = [n for n in SPHERE_NAMES if n not in found]
    if not found:
        return "no two spheres at a nominal distance: plate not recognised"
    return "sphere" + ("s " if len(missing) > 1 else " ") + " and ".join(missing) + " not found"


def fit_plate(
    points_S: ArrayLike,
    cfg: CalibrationConfig,
    *,
    normals_S: ArrayLike | None = None,
    noise_mm: float = 0.05,
    rng: np.random.Generator | None = None,
) -> PlateFit:
    """Find spheres A, X, Y in a scan (frame S, mm) and return ``T_S_P`` with residuals.

    Raises :class:`PlateError` naming the missing sphere(s) when the scan does not show all three.
    """
    P = np.asarray(points_S, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3:
        raise PlateError(f"points must be (N, 3), got {P.shape}")
    rng = rng if rng is not None else np.random.default_rng(0)
    r0 = cfg.sphere_diameter_mm / 2.0
    nominal = nominal_centres_P(cfg)
    cands = sphere_candidates(P, r0, normals_S)
    tree = cKDTree(P)
    fits: list[SphereFit] = []
    for c in cands[:8]:
        near = P[tree.query_ball_point(c, r0 + 2.0)]
        near = near[np.abs(np.linalg.norm(near - c, axis=1) - r0) < 2.0]
        try:
            f = fit_sphere(near, r0, noise_mm=noise_mm, fixed_radius=cfg.fit_fixed_radius, rng=rng)
        except PlateError as e:
            log.debug("candidate at %s rejected: %s", np.round(c, 1), e)
            continue
        if abs(f.free_radius_mm - r0) > cfg.radius_tolerance_mm:
            log.info("sphere candidate at %s: radius %.3f mm, nominal %.3f mm: rejected", np.round(c, 1),
                     f.free_radius_mm, r0)
            continue
        fits.append(f)
    centres = [f.centre for f in fits]
    match = _match_layout(centres, nominal, cfg.layout_tolerance_mm)
    if match is None:
        raise PlateError(
            f"plate scan: {_missing_spheres(centres, nominal, cfg.layout_tolerance_mm)} "
            f"({len(fits)} sphere(s) of radius {r0:.2f} mm found)"
        )
    names, residuals = match
    spheres = {n: fits[i] for n, i in names.items()}
    centres = np.stack([spheres[n].centre for n in SPHERE_NAMES])
    T = plate_frame(*centres)
    cov = plate_frame_covariance(centres, [spheres[n].centre_covariance for n in SPHERE_NAMES])
    return PlateFit(T_S_P=T, spheres=spheres, layout_residuals_mm=residuals, covariance=cov)


def plate_frame_covariance(centres: ArrayLike, centre_errors: ArrayLike, step_mm: float = 1e-4) -> np.ndarray:
    """6x6 covariance of Eq. 7-8's ``T_S_P`` (translation mm, rotation rad; left perturbation in S).

    ``centre_errors``: per sphere A, X, Y either a 1-sigma (mm, isotropic) or a 3x3 covariance (mm^2, frame S).
    """
    C = np.asarray(centres, dtype=float)
    E = np.asarray(centre_errors, dtype=float)
    if E.shape == (3,):
        E = np.square(E)[:, None, None] * np.eye(3)
    if E.shape != (3, 3, 3):
        raise ValueError(f"centre_errors must be 3 sigmas or 3 3x3 covariances, got shape {E.shape}")
    J = plate_frame_jacobian(C, step_mm)
    cov_c = np.zeros((9, 9))
    for k in range(3):
        cov_c[3 * k : 3 * k + 3, 3 * k : 3 * k + 3] = E[k]
    return J @ cov_c @ J.T


def plate_frame_jacobian(centres: ArrayLike, step_mm: float = 1e-4) -> np.ndarray:
    """6x9 derivative of Eq. 7-8's ``T_S_P`` (translation mm, rotation rad; left perturbation in S) by the
    centres A, X, Y (frame S, mm), by central differences."""
    C = np.asarray(centres, dtype=float)
    T0 = plate_frame(*C)
    J = np.empty((6, 9))
    for j in range(9):
        cols = []
        for h in (step_mm, -step_mm):
            Cp = C.copy()
            Cp[j // 3, j % 3] += h
            T = plate_frame(*Cp)
            dR = T[:3, :3] @ T0[:3, :3].T
            # rotation vector of the tiny dR: its skew part (exact to third order in the step)
            rv = 0.5 * np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]])
            cols.append(np.r_[T[:3, 3] - dR @ T0[:3, 3], rv])
        J[:, j] = (cols[0] - cols[1]) / (2 * step_mm)
    return J
