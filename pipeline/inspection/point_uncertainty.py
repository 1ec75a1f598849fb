"""Per-point expanded uncertainty U of the deviation from CAD (docs/verdict.md, "Per-point uncertainty").

Every point's deviation is its signed distance along the CAD normal ``n`` (frame F, mm). First order, its error is

    delta_d = n . delta_p - j . a + noise,

- ``delta_p``: the point's error from the poses of the scans merged into its voxel, each weighing its share of
  the voxel's points: scan ``i`` moved by the small world motion ``e_i`` about its origin ``o_i`` moves the point
  by ``n . (t_i + r_i x (p - o_i)) = g_i . e_i`` with ``g_i = [n, (p - o_i) x n]`` (W axes). The ``e`` of all
  scans are correlated (transfers, the mount) and jointly known as ``PoseCovariance`` (the joint refinement's
  posterior, or the tracker chain's prior with the installation's: the calibration's ``T_T_S`` covariance, or for
  nominal mounts a prior as wide as their build tolerance, ``[correction] mount_nominal_sigma_*``).
- ``j . a``: a best-fit alignment to CAD absorbs the part of the scans' errors a rigid motion ``a`` (about the
  fitted points' centroid, ``j = [n, (p - c) x n]`` in F) explains: ``a = -(J^T J)^-1 sum_q j_q delta_d_q`` over
  the fitted points, so each point's error is ``(g_p - B^T j_p) . e`` with ``B = (J^T J)^-1 sum_q j_q g_q^T``.
  RPS and "none" absorb nothing here (conservative).
- noise: the scanner errs along its ray (``[scanner] noise_sigma_mm``, the simulator's and the bound's model), a
  point of scan ``i`` along ``n`` by its noise times ``|cos|`` of ray and normal; the voxel's mean of ``c`` points
  has the variance ``sigma^2 sum_i w_i cos_i^2 / c`` (the cosines of the nearest centre, ``c`` the point's own).
- the alignment's own covariance (6x6 about a centre in F; a best fit's: its residuals' scatter through its normal
  matrix, ``alignment.covariance``): where the alignment states one; otherwise this term is zero and the budget
  says so.

U = k sqrt(sum of the variances). The pose terms are smooth over the surface: they are evaluated at an even
thinning of the cloud (at most :data:`MAX_CENTRES`) and each point takes its nearest centre's; the noise is each
point's own.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from scipy.spatial import cKDTree
from tandemscan.pipeline.geometry.frames import invert, rotate_vectors, transform_points
from tandemscan.pipeline.geometry.units import extent_mm
from tandemscan.pipeline.inspection.alignment import Alignment
from tandemscan.pipeline.inspection.deviation_areas import even_centres
from tandemscan.pipeline.registration.pose_covariance import PARTS, PoseCovariance, ScanErrors

MAX_CENTRES = 40_000  # pose terms are evaluated at an even thinning of at most about this many points
SCANS_PER_POINT = 4  # a point's voxel takes at most this many scans into account (the largest shares)
NEIGHBOURS = 16  # nearest points of the scans' thinned copies that tell a point which scans cover it
FIT_POINTS = 50_000  # the best fit's absorption is formed over an even subsample of this many points
ROWS_AT_ONCE = 8192  # points a per-point pass over the whole cloud takes at a time (8 M points: 0.9 s CPU, not 1.5)

SOURCES = ("scan_poses", "installation", "scanner_noise", "alignment")


@dataclass(frozen=True)
class PointUncertainty:
    """Expanded uncertainty (coverage factor ``k``) of every point's deviation along the CAD normal, mm; the budget:
    per source the median over the points of that source's expanded uncertainty alone (``budget_mm``, sources
    :data:`SOURCES`, correlations of the pose sources counted in the total only) and a note per source where it
    needs one; ``noise_variance_mm2``: the part of each point's squared standard uncertainty that is independent
    from point to point (the scanner's noise; all of a cloud's own stated U, ``GivenUncertainty``);
    ``scan_of_point``: the scan with the largest share of each point (index into the job's scans; None where not
    known)."""

    k: float
    expanded_mm: np.ndarray = field(repr=False)
    noise_variance_mm2: np.ndarray = field(repr=False)  # (N,) the share of u^2 that averaging neighbours reduces
    budget_mm: dict[str, float] = field(default_factory=dict)
    notes: dict[str, str] = field(default_factory=dict)
    scan_of_point: np.ndarray | None = field(default=None, repr=False)

    def summary(self) -> dict:
        """report.json ``inspection.uncertainty``: ``{"k", "median_mm", "p95_mm", "budget_mm", "notes"}``."""
        u = self.expanded_mm
        return {"k": self.k, "median_mm": float(np.median(u)) if len(u) else 0.0,
                "p95_mm": float(np.percentile(u, 95)) if len(u) else 0.0,
                "budget_mm": {s: round(v, 5) for s, v in self.budget_mm.items()}, "notes": dict(self.notes)}


@dataclass(frozen=True)
class AlignmentCovariance:
    """A 6x6 covariance of the alignment's small rigid motion about ``centre_mm`` (F; t mm^2, then r rad^2)."""

    covariance: np.ndarray
    centre_mm: np.ndarray


def alignment_covariance(alignment: Alignment) -> AlignmentCovariance | None:
    """The alignment's own covariance where it states one (a best fit's, ``alignment.covariance``), else None."""
    if alignment.covariance is None or alignment.covariance_centre_F_mm is None:
        return None
    return AlignmentCovariance(np.asarray(alignment.covariance, float),
                               np.asarray(alignment.covariance_centre_F_mm, float))


class UncertaintyModel(Protocol):
    """What knows the uncertainty of a cloud's points: evaluated once the cloud is aligned and its CAD normals are
    known (``points_F``, ``normals_F``; ``kept``: which of the cloud's points, as it came, are these)."""

    def evaluate(self, points_F: np.ndarray, normals_F: np.ndarray, k: float, T_F_W: np.ndarray,
                 method: str, kept: np.ndarray | None, alignment: AlignmentCovariance | None
                 ) -> PointUncertainty: ...


def _alignment_variance(points_F: np.ndarray, normals_F: np.ndarray, alignment: AlignmentCovariance | None
                        ) -> np.ndarray:
    """Each point's variance along its normal from the alignment's own covariance (0 without one), mm^2."""
    if alignment is None:
        return np.zeros(len(points_F))
    cov = np.asarray(alignment.covariance, float)
    out = np.empty(len(points_F))
    for lo in range(0, len(points_F), ROWS_AT_ONCE):  # a chunk's temporaries stay in the cache (the same numbers)
        rows = slice(lo, lo + ROWS_AT_ONCE)
        j = np.hstack([normals_F[rows], np.cross(points_F[rows] - alignment.centre_mm, normals_F[rows])])
        out[rows] = np.einsum("ij,ij->i", j @ cov, j)  # j cov j^T per row: a third of a three-operand einsum
    return out


ALIGNMENT_NOTE = "the alignment states no covariance of its own: term 0 (a best fit's absorption of the scans' " \
                 "errors is in scan_poses and installation)"


OWN_ALIGNMENT_NOTE = "the alignment's own covariance (a best fit's residual scatter through its normal matrix)"


@dataclass(frozen=True)
class GivenUncertainty:
    """A cloud's own expanded uncertainty (per point (N,) or one for all, mm, coverage factor ``k``): a scanner's
    statement (``tandemscan inspect --point-uncertainty-mm``, a PLY property ``uncertainty_mm``), taken as
    independent from point to point (a deviation averaged over n points has 1/sqrt(n) of it); the alignment's is
    added."""

    expanded_mm: np.ndarray | float
    k: float = 2.0

    def evaluate(self, points_F: np.ndarray, normals_F: np.ndarray, k: float, T_F_W: np.ndarray,
                 method: str, kept: np.ndarray | None, alignment: AlignmentCovariance | None) -> PointUncertainty:
        """U with coverage factor ``k`` of the points (the cloud's own, with its ``k``, and the alignment's)."""
        own = np.broadcast_to(np.asarray(self.expanded_mm, float), (len(kept) if kept is not None else
                                                                    len(points_F),))
        own = own[kept] if kept is not None and own.ndim and len(own) == len(kept) else own
        own = np.broadcast_to(own, (len(points_F),)) / self.k
        aligned = _alignment_variance(points_F, normals_F, alignment)
        total = k * np.sqrt(own**2 + aligned)
        budget = {"cloud": float(np.median(k * own)) if len(own) else 0.0,
                  "alignment": float(np.median(k * np.sqrt(aligned))) if len(own) else 0.0}
        notes = {"cloud": "the cloud's own expanded uncertainty as given"}
        notes["alignment"] = ALIGNMENT_NOTE.split(" (")[0] if alignment is None else OWN_ALIGNMENT_NOTE
        return PointUncertainty(k, total, own**2, budget, notes)


#: held while a :class:`ScanCover` finds its scans' extents, so that the threads asking for them find them once
_EXTENTS = threading.Lock()
#: :meth:`ScanCover.shares` answers its queries a slab of W across x this wide (mm) at a time, from a KD tree of the
#: scans' thinned points within reach of the slab: the tree is bounded by the slab, not by the part's scans
COVER_SLAB_MM = 500.0
#: how far beyond its slab (mm) a slab's tree first reaches; the queries whose nearest points it cannot prove nearest
#: of all are asked again of a tree reaching four times as far
COVER_REACH_MM = 20.0


@dataclass(frozen=True)
class ScanCover:
    """Which scans' points a cloud's points were merged from: the scans' thinned copies (``points_S``, each in its
    scanner frame S, mm) placed in W by their poses ``T_W_S`` (4x4, mm), each scan's full point count, its origin
    (the scanner's optical centre, W, mm) and index in the job's scans."""

    points_S: Sequence[np.ndarray]
    T_W_S: Sequence[np.ndarray]
    point_counts: np.ndarray
    origins_mm: np.ndarray
    scan_ids: np.ndarray

    @property
    def _extents(self) -> tuple[np.ndarray, np.ndarray]:
        """Each scan's thinned point count and the x extent (W, mm; (K, 2), inf and -inf without points) of its
        points placed, found once: by the first thread that asks (:meth:`prepared`'s, or the caller's), any other
        waiting for them (:data:`_EXTENTS`)."""
        with _EXTENTS:
            if "_found_extents" not in self.__dict__:
                sizes = np.array([len(p) for p in self.points_S], np.int64)
                object.__setattr__(self, "_found_extents", (sizes, x_extents(self.points_S, self.T_W_S)))
        return self.__dict__["_found_extents"]

    def prepared(self) -> ScanCover:
        """This cover with its scans' extents being found on a thread of its own: made as the job's inspection
        starts, it needs none of it, and the points' U finds them (or waits for them)."""
        threading.Thread(target=lambda: self._extents, name="scan-cover-extents", daemon=True).start()
        return self

    def _slab(self, x0_mm: float, x1_mm: float) -> tuple[np.ndarray, np.ndarray, cKDTree]:
        """(scans, ends, tree): the scans (positions in this cover) with thinned points of x in ``[x0_mm, x1_mm]``
        (W), where each one's such points end in the tree's (their cumulative counts: a point's scan is found from
        its index) and a KD tree of those points."""
        _, extents = self._extents
        scans = np.flatnonzero((extents[:, 1] >= x0_mm) & (extents[:, 0] <= x1_mm))
        parts = []
        for i in scans:
            placed = transform_points(self.T_W_S[i], self.points_S[i])
            parts.append(placed[(placed[:, 0] >= x0_mm) & (placed[:, 0] <= x1_mm)])
        ends = np.cumsum([len(p) for p in parts], dtype=np.int64)
        points = np.concatenate(parts) if parts else np.empty((0, 3))
        del parts
        return scans, ends, cKDTree(points, leafsize=32, balanced_tree=False)

    def shares(self, points_W: np.ndarray, k: int = SCANS_PER_POINT) -> tuple[np.ndarray, np.ndarray]:
        """(M, k) scan positions (into this cover's scans) and their shares of each point's voxel (rows sum to
        1): the scans among the :data:`NEIGHBOURS` nearest thinned points, each weighing its points found there
        times its thinning ratio (full points over thinned ones), the ``k`` largest kept. Asked a slab of
        :data:`COVER_SLAB_MM` at a time (:meth:`_slab`): a query's nearest points in a slab's tree are its nearest of
        all where the farthest of them is nearer than the tree's reach beyond the query's x; the others are asked
        again of a tree reaching farther (the same answers as one tree of every scan's points)."""
        points_W = np.asarray(points_W, float)
        sizes, _ = self._extents
        kn, kk = min(NEIGHBOURS, int(sizes.sum())), min(k, len(sizes))
        ratio = np.asarray(self.point_counts, float) / np.maximum(sizes, 1)
        top, w = np.empty((len(points_W), kk), np.int64), np.empty((len(points_W), kk))
        x = points_W[:, 0]
        slab = np.floor(x / COVER_SLAB_MM)
        for s in np.unique(slab):
            rows, reach = np.flatnonzero(slab == s), COVER_REACH_MM
            while len(rows):
                x0, x1 = s * COVER_SLAB_MM - reach, (s + 1) * COVER_SLAB_MM + reach
                scans, ends, tree = self._slab(x0, x1)
                if tree.n < kn:
                    reach *= 4.0
                    continue
                dist, idx = (a.reshape(-1, kn) for a in tree.query(points_W[rows], k=kn, workers=-1))
                proven = (dist[:, -1] < np.minimum(x[rows] - x0, x1 - x[rows])) | (tree.n == sizes.sum())
                near = scans[np.searchsorted(ends, idx[proven], side="right")]  # each neighbour's scan
                top[rows[proven]], w[rows[proven]] = _largest_votes(near, ratio, kk)
                rows, reach = rows[~proven], reach * 4.0
        return top, w / w.sum(axis=1, keepdims=True)


def x_extents(points_S: Sequence[np.ndarray], T_W_S: Sequence[np.ndarray]) -> np.ndarray:
    """(K, 2) the x extent (W, mm) of each scan's points ``points_S`` (S, mm) placed at its ``T_W_S``; (inf, -inf)
    for a scan without points."""
    extents = np.tile([np.inf, -np.inf], (len(points_S), 1))
    for i, (points, T) in enumerate(zip(points_S, T_W_S, strict=True)):
        if len(points):
            x = transform_points(T, points)[:, 0]
            extents[i] = x.min(), x.max()
    return extents


def _largest_votes(near: np.ndarray, ratio: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Per row of ``near`` ((M, n) each query's nearest points' scans) the ``k`` scans of the most votes (each of its
    points votes its scan's thinning ratio ``ratio``) and their votes, (M, k) each."""
    top, w = np.empty((len(near), k), np.int64), np.empty((len(near), k))
    step = max(1, 20_000_000 // (8 * max(len(ratio), 1)))  # dense votes of a chunk: about 20 MB
    for lo in range(0, len(near), step):
        chunk = near[lo:lo + step]
        votes = np.zeros((len(chunk), len(ratio)))
        np.add.at(votes, (np.repeat(np.arange(len(chunk)), chunk.shape[1]), chunk.ravel()), ratio[chunk.ravel()])
        top[lo:lo + step] = np.argsort(-votes, axis=1)[:, :k]
        w[lo:lo + step] = np.take_along_axis(votes, top[lo:lo + step], axis=1)
    return top, w


@dataclass(frozen=True)
class JobUncertainty:
    """The uncertainty model of a job's cloud (module doc): its scans' pose errors jointly (``poses``), which
    scans each point came from (``cover``), the points merged into each voxel (``counts``, (N,) of the cloud as
    given to the inspection, None: one) and the scanner's noise along its ray (``noise_sigma_mm``, 1 sigma)."""

    poses: PoseCovariance
    cover: ScanCover
    noise_sigma_mm: float
    counts: np.ndarray | None = None

    def evaluate(self, points_F: np.ndarray, normals_F: np.ndarray, k: float, T_F_W: np.ndarray,
                 method: str, kept: np.ndarray | None, alignment: AlignmentCovariance | None) -> PointUncertainty:
        """U (coverage factor ``k``) of the points ``points_F`` (F, mm) with CAD normals ``normals_F``, placed by
        ``T_F_W`` with the alignment ``method``; ``kept`` selects them from the cloud as given (None: all)."""
        p_F, n_F = np.asarray(points_F, float), np.asarray(normals_F, float)
        T_W_F = invert(np.asarray(T_F_W, float))
        counts = np.ones(len(p_F)) if self.counts is None else np.asarray(self.counts, float)
        if kept is not None and self.counts is not None:
            counts = counts[kept]
        cell = _centre_cell(p_F)
        centres = even_centres(p_F, cell)
        nearest = _nearest_centre(p_F, centres, cell)
        fit = (np.arange(len(p_F))[:: max(1, len(p_F) // FIT_POINTS)] if method == "best-fit"
               else np.zeros(0, np.int64))
        # only the centres and the best fit's points are needed in W, and their scans are found in one pass of the
        # cover's slabs (each row's answer is its own: the same as two passes)
        asked = np.concatenate([centres, fit])
        p_W, n_W = transform_points(T_W_F, p_F[asked]), rotate_vectors(T_W_F, n_F[asked])
        top, w = self.cover.shares(p_W)
        m = len(centres)
        c_at = top[:m], w[:m]
        noise = (self.noise_sigma_mm**2 * self._ray_cosines_sq(p_W[:m], n_W[:m], c_at))[nearest]
        noise /= np.maximum(counts, 1.0)
        absorb = None
        if method == "best-fit":
            absorb = self._absorption(p_W[m:], n_W[m:], p_F[fit], n_F[fit], (top[m:], w[m:]))
        errors = self.poses.scan_errors(_covering_pairs(np.maximum(self._pose_rows()[c_at[0]], 0)))
        absorbed = None if absorb is None else _Absorbed.of(self.poses, *absorb)
        parts = {part: v[nearest] for part, v in self._pose_variances(errors, p_W[:m], n_W[:m],
                                                                      p_F[centres], n_F[centres], c_at,
                                                                      absorbed).items()}
        aligned = _alignment_variance(p_F, n_F, alignment)
        total = k * np.sqrt(parts["all"] + noise + aligned)
        budget = {"scan_poses": parts["scan_poses"], "installation": parts["installation"],
                  "scanner_noise": noise, "alignment": aligned}
        notes = {"scan_poses": f"{self.poses.source}: tracker readings, transfers"
                 + (", less what the best fit absorbs" if absorb is not None else ""),
                 "installation": "scanner mount T_T_S" + ("" if self.poses.installation_columns else
                                                          ": not modelled (no mount prior)"),
                 "scanner_noise": f"{self.noise_sigma_mm:g} mm (1 sigma) along the ray, averaged in the voxel"}
        notes["alignment"] = ALIGNMENT_NOTE if alignment is None else OWN_ALIGNMENT_NOTE
        scan_ids = self.cover.scan_ids[c_at[0][:, 0]][nearest]
        return PointUncertainty(k, total, noise, {s: float(np.median(k * np.sqrt(v))) for s, v in budget.items()},
                                notes, scan_ids)

    def _ray_cosines_sq(self, p_W: np.ndarray, n_W: np.ndarray, at: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """``sum_i w_i cos_i^2`` per point: cos_i of the ray from scan i's origin and the normal."""
        idx, w = at
        rays = p_W[:, None, :] - self.cover.origins_mm[idx]
        cos = np.einsum("ikj,ij->ik", rays, n_W) / np.maximum(np.linalg.norm(rays, axis=2), 1e-9)
        return np.sum(w * cos**2, axis=1)

    def _gradients(self, p_W: np.ndarray, n_W: np.ndarray, at: tuple[np.ndarray, np.ndarray]
                   ) -> tuple[np.ndarray, np.ndarray]:
        """(M, K) rows into the pose covariance's scans and (M, K, 6) ``w_i g_i`` of each point (module doc)."""
        idx, w = at
        rows = self._pose_rows()[idx]
        lever = p_W[:, None, :] - self.poses.origins_mm[np.maximum(rows, 0)]
        g = np.concatenate([np.broadcast_to(n_W[:, None, :], lever.shape), np.cross(lever, n_W[:, None, :])], axis=2)
        return np.maximum(rows, 0), g * (w * (rows >= 0))[:, :, None]

    def _pose_rows(self) -> np.ndarray:
        """Per scan of the cover its position in the pose covariance (-1: not in it, a scan that saw nothing)."""
        where = {int(s): i for i, s in enumerate(self.poses.scan_ids)}
        return np.array([where.get(int(s), -1) for s in self.cover.scan_ids])

    def _absorption(self, p_W: np.ndarray, n_W: np.ndarray, p_F: np.ndarray, n_F: np.ndarray,
                    at: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """``(B, c)``: the best fit's rigid motion about ``c`` (F) from the scans' errors, ``a = -B e``."""
        c = p_F.mean(axis=0)
        j = np.hstack([n_F, np.cross(p_F - c, n_F)])
        rows, g = self._gradients(p_W, n_W, at)
        S = np.zeros((6, len(self.poses.scan_ids), 6))
        for kk in range(rows.shape[1]):
            np.add.at(S, (slice(None), rows[:, kk]), np.einsum("qa,qb->aqb", j, g[:, kk]))
        JtJ = j.T @ j
        return np.linalg.solve(JtJ + 1e-9 * np.trace(JtJ) * np.eye(6), S.reshape(6, -1)), c

    def _pose_variances(self, errors: ScanErrors, p_W: np.ndarray, n_W: np.ndarray, p_F: np.ndarray,
                        n_F: np.ndarray, at: tuple[np.ndarray, np.ndarray], absorbed: dict[str, _Absorbed] | None
                        ) -> dict[str, np.ndarray]:
        """Per part (``pose_covariance.PARTS``) each point's variance along its normal from the pose errors
        (``PoseCovariance.scan_errors``), less the best fit's absorption where given, mm^2: with ``v = g - B^T j``
        (``g`` a point's weighted gradients, nonzero at its few scans only), ``v^T cov v = g^T cov g - 2 g^T cov B^T
        j + j^T B cov B^T j``, the first term from the blocks of its scans (no product with the whole ``cov``)."""
        out = {part: np.empty(len(p_W)) for part in PARTS}
        step = 2048
        for lo in range(0, len(p_W), step):
            sl = slice(lo, lo + step)
            rows, g = self._gradients(p_W[sl], n_W[sl], (at[0][sl], at[1][sl]))
            j = np.hstack([n_F[sl], np.cross(p_F[sl] - absorbed["all"].centre_mm, n_F[sl])]) if absorbed else None
            for part, var in errors.variances(rows, g).items():
                if absorbed is not None:
                    var -= 2.0 * np.einsum("mkj,mkjq,mq->m", g, absorbed[part].cov_B[rows], j)
                    var += np.einsum("ma,ab,mb->m", j, absorbed[part].B_cov_B, j)
                out[part][sl] = np.maximum(var, 0.0)  # rounding may take an absorbed variance below 0
        return out


def _nearest_centre(points_F: np.ndarray, centres: np.ndarray, cell_mm: float) -> np.ndarray:
    """Per point (F, mm) the index into ``centres`` (:func:`even_centres` at ``cell_mm``) of its nearest centre. Its
    own cube's centre is at most a cube's diagonal away, so the search stops there (a quarter less CPU, the same
    answers)."""
    if len(centres) == len(points_F):
        return np.arange(len(points_F))
    bound_mm = cell_mm * math.sqrt(3.0) * (1.0 + 1e-9)
    return cKDTree(points_F[centres]).query(points_F, workers=-1, distance_upper_bound=bound_mm)[1]


@dataclass(frozen=True)
class _Absorbed:
    """What a best fit takes of one part's pose errors (``JobUncertainty._absorption``'s ``B`` about ``centre_mm``):
    ``cov B^T`` per scan (n, 6, 6: a scan's error against the fit's motion) and ``B cov B^T`` (6, 6)."""

    cov_B: np.ndarray
    B_cov_B: np.ndarray
    centre_mm: np.ndarray

    @classmethod
    def of(cls, poses: PoseCovariance, B: np.ndarray, centre_mm: np.ndarray) -> dict[str, _Absorbed]:
        """Per part (``pose_covariance.PARTS``) from ``B`` (6, 6n) and the part's covariance applied by solves
        (``PoseCovariance.times``)."""
        return {part: cls(cov_B.reshape(-1, 6, 6), B @ cov_B, centre_mm)
                for part, cov_B in poses.times(B.T).items()}


def _covering_pairs(rows: np.ndarray) -> np.ndarray:
    """(P, 2) the pairs of scan rows that share a point (``rows``: (M, K) each point's scans), each once."""
    a, b = np.triu_indices(rows.shape[1], 1)
    lo, hi = np.minimum(rows[:, a], rows[:, b]).ravel(), np.maximum(rows[:, a], rows[:, b]).ravel()
    n = int(rows.max()) + 1 if rows.size else 1
    keys = np.unique(hi[hi != lo] * n + lo[hi != lo])
    return np.stack([keys // n, keys % n], axis=1)


def _centre_cell(points_F: np.ndarray) -> float:
    """Cube edge (mm) of the even thinning the pose terms are evaluated on: about :data:`MAX_CENTRES` cubes on a
    surface of the cloud's extent (1 mm at least)."""
    extent = extent_mm(points_F) if len(points_F) else np.ones(3)
    area = float(np.sort(extent)[-2:].prod()) * 2.0  # a sheet of the two largest extents, curved: about twice
    return max(1.0, math.sqrt(area / MAX_CENTRES))
