"""Joint multi-view refinement: every scan pose, the transfer errors and the shared mount fitted together on the
overlap points themselves (docs/correction.md, "Joint refinement").

The pose graph (``pose_graph``) summarises each registered pair by one relative pose and a fixed information
matrix; it inherits each pair's own bias. Here every overlap point is a point-to-plane measurement between its
two scans, so that the adjustment uses the same data the Cramer-Rao bound of the job
(``benchmarks/pose_bound.py``) assumes.

The first linearisation takes the correspondences found at the start poses (the tracker poses, which do not
depend on the scans' noise; a job finds them while it measures: :func:`associate`, ``online_pairs``).
``JointSettings.reassociate_mm`` finds anew, before each later linearisation, the correspondences of the pairs that
have moved. A job runs two passes (``[correction] joint_iterations`` 2, ``joint_reassociate_mm`` 0.02): the first
one's weights and correspondences are the start's (its residuals' scale holds the tracker's misalignment: whole
part, seed 7, 0.093 mm whitened against the noise's 0.071), the second's are the data's own at poses within the
posterior of the truth. Measured on seeds 7-9 of the whole part, a third pass changes the figures by 1-2 % either
way (docs/correction.md, "What the measurements showed"; before the weights' sigma was whitened, a
second pass cost seed 8, "Association anew after the first linearisation").

Model (first order in the small corrections, world axes, mm and rad; every 6-vector is (t, rotation vector)):
the unknowns ``theta`` are a world motion ``x_i`` of each scan about its origin ``o_i`` (prior: the tracker
covariance ``ScanPrior.covariance``), a world motion ``y_k`` of each coordinate transfer about the still target
``c_k`` (prior ``TransferPrior.covariance``; station ``s`` carries every transfer ``k <= s``) and, with a
``MountPrior``, the shared right-perturbation ``D = Exp(L u)`` of ``T_T_S`` (``u`` whitened by the prior's
Cholesky factor ``L``). Scan ``i`` is corrected by the world motion about ``o_i``

    e_i = x_i + sum_{k <= s_i} Ad(c_k -> o_i) y_k + blockdiag(R_i, R_i) L u,   T_W_S_i = Tr(o_i) Exp(e_i) Tr(-o_i) P_i

(``P_i`` the tracker pose, ``R_i`` its rotation), i.e. ``e = A theta``, the error model of the bound. A point
``p`` of scan ``j`` whose nearest neighbour in scan ``i`` (within ``max_distance_mm``) is ``q`` gives the residual
``n . (T_W_S_j p - T_W_S_i q)``, ``n`` the mean of the two points' unit normals (at the current poses; kept
where they agree within ``MIN_NORMAL_COSINE``): the symmetric point-to-plane residual, zero for two points of
one circular arc, where the plane of ``q`` alone leaves the arc's sagitta (curvature times the squared offset,
halved). Its variance follows the scanner's noise along its rays and the measured points each of the two
thinned points averages (``ray_variances``, ``JointScan.counts``), and where more than two
scans cover a place their pairs share each scan's noise (``noise_shares``): each residual weighs its share over its
variance. Each linearisation weights the residuals at the current poses (Huber at ``huber_k`` times their robust
scale; the sigma of two points seen head-on from the residuals whitened by their relative variance, ``_whitened``)
and solves the sparse normal
equations ``(A^T H_e A + prior) theta = A^T (H_e e - b_e)`` (``e`` the corrections so far, ``b_e`` the weighted
residuals' gradient) for ``theta`` itself (scipy.sparse); the posterior covariance of
each scan's correction is ``A_i C A_i^T``, ``C`` the covariance of ``theta`` under the residuals' noise at the
refined poses (``_posterior``: a sigma taken at the start poses also holds the start's misalignment,
and ``H^-1`` alone was that much too wide: whole part, seed 7, one linearisation, 0.093 against 0.071 mm).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import logging
import math
import os
import pickle
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
from scipy import sparse
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree
from tandemscan.pipeline.compute import ComputeBackend, LocalBackend
from tandemscan.pipeline.geometry.frames import from_rotvec, invert, rotate_vectors, to_rotvec, transform_points
from tandemscan.pipeline.geometry.uncertainty import recentre
from tandemscan.pipeline.geometry.units import box_mm
from tandemscan.pipeline.parameters import FromSection
from tandemscan.pipeline.registration.icp import RefineError
from tandemscan.pipeline.registration.mount_unknown import MountEstimate, MountPrior
from tandemscan.pipeline.registration.pose_covariance import PoseCovariance
from tandemscan.pipeline.registration.pose_graph import ScanPrior, TransferPrior

log = logging.getLogger(__name__)

#: a correspondence counts only where the two scans' normals agree within 5 deg. A normal estimated from a
#: one-sided neighbourhood (a scan's border, a silhouette) or across a crease is tilted by it, and its plane
#: then misplaces a point by the tilt times the point's offset along the surface; such points are a few in a
#: thousand, but their residuals are biased alike and act through the lever arms of the weakly held
#: transfers (whole part, seed 7: 0.061 -> 0.055 mm at 30 -> 5 deg, 0.05 % of the correspondences; the normal's
#: own noise at 2 mm voxels is about 0.2 deg). docs/correction.md, "Joint refinement".
MIN_NORMAL_COSINE = float(np.cos(np.radians(5.0)))

#: the scanner errs along its rays from the origin of S (the camera's optical centre: the PhoXi's camera space,
#: the simulator's model), so a point errs along a residual's normal n by its noise times ``|n . ray|``; a
#: residual's variance is the sum of its two points' (:func:`ray_variances`). The sum of the two squared cosines
#: is taken as at least this: a grazing pair counts at most ten times a head-on one (each cosine 1, sum 2).
MIN_RAY_COSINES_SQ = 0.2

#: a group of pairs tests its dispersion (:func:`_dispersions`) only where it leaves at least this many degrees of
#: freedom of its residuals' rigid-motion chi-square to the test: a chi-square of 30 scatters by 26 % about its
#: mean, and with fewer the factor would be mostly its own noise (the band plan's pairs across two stations,
#: four pairs, leave about 18; the whole part's groups hundreds)
MIN_REDUNDANCY = 30.0

#: a robust scale (mm) never below this (0.1 um, far below any scanner noise): noiseless data would otherwise
#: weight every point without bound and make the normal equations singular in floating point
_MIN_SIGMA_MM = 1e-4


def _cross(a: np.ndarray, b: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Row-wise cross product of two (m, 3) arrays (np.cross is several times slower on short rows), written into
    ``out`` ((m, 3), e.g. three columns of a larger array) where given."""
    out = np.empty((len(a), 3)) if out is None else out
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _row_dots(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products of two (m, 3) arrays, summed in ``np.einsum("ij,ij->i")``'s order (x, z, then y: the
    same bits) in about half its time on a pair's thousands of rows."""
    out = a[:, 0] * b[:, 0]
    out += a[:, 2] * b[:, 2]
    out += a[:, 1] * b[:, 1]
    return out


@dataclass(frozen=True)
class JointScan:
    """One scan for the joint solve: its (thinned) points and unit normals in the scanner frame S (mm), and
    ``counts``, how many measured points each thinned one averages (a voxel centroid of ``n`` errs by
    ``1 / sqrt(n)`` of one point's noise; None: one each)."""

    points_S: np.ndarray
    normals_S: np.ndarray
    counts: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.counts is not None and (len(self.counts) != len(self.points_S) or np.any(self.counts < 1)):
            raise ValueError(f"joint scan: {len(self.counts)} counts for {len(self.points_S)} points, each at least "
                             "one measured point is needed")

    @classmethod
    def from_points(cls, points_S: np.ndarray, normal_neighbours: int = 20, counts: np.ndarray | None = None
                    ) -> JointScan:
        """The scan with unit normals estimated from its ``normal_neighbours`` nearest points (Open3D: three
        times faster than ``normals.estimate_normals`` on a scan of 30 k points, the same normals)."""
        P = np.asarray(points_S, float)
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(normal_neighbours))
        return cls(P, np.asarray(cloud.normals), None if counts is None else np.asarray(counts, float))

    def counts_at(self, indices: np.ndarray) -> np.ndarray | None:
        """``counts`` of the points at ``indices`` (None where the scan has none: one each)."""
        return None if self.counts is None else self.counts[indices]


@dataclass(frozen=True)
class StoredJointScan:
    """A :class:`JointScan` kept in a file of the job's scan store (``path``, written once where its scan was read:
    :meth:`write`) and read by each unit that takes it (:func:`loaded_scan`): on a Dask cluster no worker holds the
    scans between the refinement's units, so that a worker's memory is bounded by a unit's, not by its share of the
    part (docs/compute.md). ``key`` names its contents (``correction.joint_scan_key``)."""

    path: str
    key: str

    @classmethod
    def write(cls, scan: JointScan, path: Path, key: str) -> StoredJointScan:
        """``scan`` written to ``path`` (uncompressed npz; through a temporary file, so that a unit run twice, or
        two scans of the same points, never leave a partial file)."""
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {"points_S": scan.points_S, "normals_S": scan.normals_S}
        if scan.counts is not None:
            arrays["counts"] = scan.counts
        tmp = path.with_name(f"{path.name}.{os.getpid()}-{threading.get_ident()}.tmp")
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
        os.replace(tmp, path)
        return cls(str(path), key)

    def read(self) -> JointScan:
        """The scan, as it was written (the same bits; one of the few read last where it is among them,
        :data:`RECENT_SCANS`)."""
        return _read_stored(self)

    def remove(self) -> None:
        """Remove its file (once the refinement is done)."""
        Path(self.path).unlink(missing_ok=True)


#: stored scans a process keeps once read, and KD-trees of them (the latest used): consecutive units share scans (a
#: target's pairs run one after another), and these few (about 2.8 MB a scan at full resolution, 1.6 MB a tree) keep
#: a worker's memory independent of the part's scans
RECENT_SCANS, RECENT_TREES = 8, 4


@functools.lru_cache(maxsize=RECENT_SCANS)
def _read_stored(scan: StoredJointScan) -> JointScan:
    with np.load(scan.path) as data:
        return JointScan(data["points_S"], data["normals_S"], data["counts"] if "counts" in data else None)


@functools.lru_cache(maxsize=RECENT_TREES)
def _stored_tree(scan: StoredJointScan) -> cKDTree:
    """:func:`joint_tree` of a stored scan (one of the few built last where it is among them)."""
    return joint_tree(scan.read())


def loaded_scan(scan: JointScan | StoredJointScan) -> JointScan:
    """The scan a unit takes: read where it is a :class:`StoredJointScan`."""
    return scan.read() if isinstance(scan, StoredJointScan) else scan


@dataclass(frozen=True)
class JointSettings(FromSection):
    """``max_distance_mm``: a source point's nearest target point within this distance is its correspondence;
    ``huber_k``: Huber threshold in robust sigmas of the residuals as they are (with ``sigma_mm`` set: times it, a
    looser cut, the head-on sigma being above the residuals' own scale, 1.3 times on the whole part);
    ``iterations``: at most this many linearisations (at least
    one), fewer once no scan moves more than ``tolerance_mm`` (translation plus rotation at ``lever_mm``);
    ``reassociate_mm``: before each linearisation after the first, a pair whose source points have moved
    against its target scan by more than this (mm) since its correspondences were found has them found anew
    at the current poses (None: those found at the start poses are kept throughout);
    ``min_correspondences``: a pair with fewer contributes nothing in that iteration; ``sigma_mm``: 1-sigma of a
    point-to-plane residual between two points seen head-on (None: the robust scale of the residuals whitened by
    their relative variance, re-estimated in every iteration)."""

    max_distance_mm: float = 1.0
    huber_k: float = 2.5
    iterations: int = 1
    tolerance_mm: float = 1e-3
    lever_mm: float = 100.0
    min_correspondences: int = 20
    sigma_mm: float | None = None
    reassociate_mm: float | None = None

    def __post_init__(self) -> None:
        if self.iterations < 1:
            raise ValueError(f"joint refinement: {self.iterations} linearisations asked for, at least one is needed")

    @classmethod
    def from_section(cls, section: object, **given: object) -> JointSettings:
        """From ``[correction]``'s ``joint_*`` keys (``joint_max_distance_mm``, ``joint_iterations``,
        ``joint_sigma_mm``, ``joint_reassociate_mm``); the others keep their defaults."""
        return cls(**{"max_distance_mm": section.joint_max_distance_mm, "iterations": section.joint_iterations,
                      "sigma_mm": section.joint_sigma_mm, "reassociate_mm": section.joint_reassociate_mm, **given})


@dataclass(frozen=True)
class JointResult:
    """Refined ``T_W_S`` per scan; each scan's posterior covariance (6x6, t mm^2 at its origin then r rad^2,
    world axes) and prior (tracker and transfers) covariance; the mount estimate (None without a mount
    prior); figures: outer iterations, pairs and correspondences of the last one, the residuals' sigma (mm, as
    ``JointSettings.sigma_mm``) the weights used, the point-to-plane RMS (mm) of the correspondences at the start
    and at the refined poses, and their sigma at the refined poses (``noise_sigma_mm``, the same estimate as
    ``sigma_mm``), which the posterior covariances take as the noise's (``_posterior``); and the pairs
    whose correspondences were found anew after the first linearisation, summed over the linearisations (a pair
    found anew twice counts twice; ``JointSettings.reassociate_mm``)."""

    poses: list[np.ndarray]
    covariances: np.ndarray
    prior_covariances: np.ndarray
    mount: MountEstimate | None
    iterations: int
    pairs: int
    correspondences: int
    sigma_mm: float
    rms_mm_before: float
    rms_mm_after: float
    noise_sigma_mm: float
    pairs_associated_anew: int
    pose_covariance: PoseCovariance | None = None  # the posterior of every scan's error jointly (its correlations)
    #: per pair of tracker stations ("2-3"), the factor its pairs' noise information is counted at in the
    #: posterior (:func:`_dispersions`; 1 where the pairs scatter as their points' independent noise says)
    dispersion: Mapping[str, float] = dataclasses.field(default_factory=dict)


def _adjoint_blocks(R: np.ndarray) -> np.ndarray:
    """``blockdiag(R, R)``: a scanner-frame motion about the scan origin as a world motion about it."""
    M = np.zeros((6, 6))
    M[:3, :3] = M[3:, 3:] = R
    return M


class _Model:
    """The linear error model ``e = A theta`` and the prior information on ``theta`` (see the module doc)."""

    def __init__(self, priors: Sequence[ScanPrior], transfers: Sequence[TransferPrior],
                 mount_prior: MountPrior | None) -> None:
        n = self.n = len(priors)
        self.P0 = np.stack([np.asarray(p.T_W_S, float) for p in priors])
        self.origins = np.ascontiguousarray(self.P0[:, :3, 3])   # as a unit gets them (contiguous): the same bits
        stations = self.stations = np.array([p.station for p in priors])
        known = {t.station for t in transfers}
        if transfers and (len(known) != len(transfers) or min(known) <= stations.min()
                          or not set(stations) - {stations.min()} <= known):
            raise RefineError(f"transfer priors for stations {sorted(known)}: need one for each station after the "
                              f"first of {sorted(set(stations.tolist()))}, or none")
        self.transfers = sorted(transfers, key=lambda t: t.station)
        self.L = None if mount_prior is None else np.linalg.cholesky(np.asarray(mount_prior.covariance, float))
        self.mount_prior = mount_prior
        k = len(self.transfers)
        self.size = 6 * (n + k) + (0 if self.L is None else 6)
        rows, cols, vals = [], [], []

        def block(i: int, col: int, M: np.ndarray) -> None:
            r, c = np.meshgrid(np.arange(6) + 6 * i, np.arange(6) + col, indexing="ij")
            rows.append(r.ravel())
            cols.append(c.ravel())
            vals.append(M.ravel())

        for i in range(n):
            block(i, 6 * i, np.eye(6))
            for m, t in enumerate(self.transfers):
                if stations[i] >= t.station:
                    block(i, 6 * (n + m), recentre(t.centre_mm, self.origins[i]))
            if self.L is not None:
                block(i, 6 * (n + k), _adjoint_blocks(self.P0[i, :3, :3]) @ self.L)
        self.A = sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                                   shape=(6 * n, self.size))
        prior_cov = np.stack([np.asarray(c.covariance, float) for c in [*priors, *self.transfers]]
                             + ([] if self.L is None else [np.eye(6)]))
        self.prior_information = sparse.block_diag(np.linalg.inv(prior_cov), format="csr")  # one call, all blocks
        self.prior_covariance = sparse.block_diag(prior_cov, format="csr")

    def poses(self, e: np.ndarray) -> np.ndarray:
        """``T_W_S_i = Tr(o_i) Exp(e_i) Tr(-o_i) P_i`` for the stacked corrections ``e`` (n, 6)."""
        out = np.empty_like(self.P0)
        for i, (o, d) in enumerate(zip(self.origins, e, strict=True)):
            out[i] = from_rotvec(o, [0, 0, 0]) @ from_rotvec(d[:3], d[3:]) @ from_rotvec(-o, [0, 0, 0]) @ self.P0[i]
        return out

    def corrections(self, poses: Sequence[np.ndarray]) -> np.ndarray:
        """Inverse of :meth:`poses`: the (n, 6) corrections that give ``poses``."""
        out = np.empty((self.n, 6))
        for i, (o, T) in enumerate(zip(self.origins, poses, strict=True)):
            t, r = to_rotvec(from_rotvec(-o, [0, 0, 0]) @ np.asarray(T, float) @ invert(self.P0[i])
                             @ from_rotvec(o, [0, 0, 0]))
            out[i] = np.r_[t, r]
        return out

    def pose_covariance(self, normal: sparse.spmatrix, information: sparse.spmatrix, source: str) -> PoseCovariance:
        """The scans' errors ``e = A theta`` jointly, ``theta`` of covariance ``normal^-1 information normal^-1``
        (both sparse, kept so: ``PoseCovariance``), for every scan ``0 .. n-1`` (the caller maps them to its own);
        ``A`` as it is, sparse."""
        mount = () if self.L is None else tuple(range(self.size - 6, self.size))
        return PoseCovariance(np.arange(self.n), self.origins.copy(), self.A, normal, information, source, mount)

    @functools.cached_property
    def scan_columns(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per scan ``i`` the columns of ``A`` its six rows use (its reading, its station's transfers, the mount) and
        those rows there (6 x k, dense): ``e_i = A_i theta[cols]``."""
        A = self.A                                # CSR, one entry a (row, column): read from its arrays
        out = []
        for i in range(self.n):
            lo, hi = A.indptr[6 * i], A.indptr[6 * i + 6]
            cols, at = np.unique(A.indices[lo:hi], return_inverse=True)
            block = np.zeros((6, len(cols)))
            block[np.repeat(np.arange(6), np.diff(A.indptr[6 * i:6 * i + 7])), at] = A.data[lo:hi]
            out.append((cols, block))
        return out

    def scan_covariances(self, cov_theta: sparse.spmatrix) -> np.ndarray:
        """(n, 6, 6) covariance of every ``e_i`` from a sparse covariance of ``theta`` (the priors'): the diagonal
        blocks ``A_i cov A_i^T`` of ``A cov A^T`` only, each from the few columns ``A_i`` uses (:attr:`scan_columns`),
        neither the whole (6n, 6n) product nor ``A`` dense (the posterior's: ``PoseCovariance.scan_covariances``)."""
        C = sparse.csr_matrix(cov_theta)
        out = np.empty((self.n, 6, 6))
        for i, (cols, Ai) in enumerate(self.scan_columns):
            out[i] = Ai @ C[cols][:, cols].toarray() @ Ai.T
        return out


@dataclass(frozen=True)
class _Match:
    """The correspondences of one pair: the indices of the source points (scan j) and of their target points
    (scan i), and at the current poses the point-to-plane residuals (mm); fixed when they were found, each
    residual's variance relative to that of two points seen head-on (:func:`ray_variances`) and ``found_at``, the
    relative pose ``T_S_i_S_j`` they were found at (:func:`_moved_beyond`); and ``covering``, the scans that cover
    each residual's place (uint16; its share :attr:`share`, :func:`noise_shares`), counted again whenever any pair's
    correspondences are found anew. 26 bytes a correspondence: neither the source points placed in S_i nor the
    symmetric normals are kept (48 bytes more, half a GB on the whole part's 10.9 M), both found again where the
    normal equations need them (:meth:`_Pair.normal_equations`, the same bits); ``found``, the search they came
    from where it tells a later one which points to search again (:attr:`Association.reach_mm`; else None), held
    until the pair's correspondences are found anew; at the refined poses ``unit_system``, the pair's normal
    equations there with each residual weighted by its relative variance alone (:func:`_refined`; else None)."""

    source: np.ndarray
    target: np.ndarray
    residual: np.ndarray
    variance: np.ndarray
    covering: np.ndarray
    found_at: np.ndarray
    found: Association | None = None
    unit_system: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def share(self) -> np.ndarray:
        """Each residual's share of its information (:func:`noise_shares` of :attr:`covering`)."""
        return noise_shares(self.covering)


class _Pair:
    """A scan pair ``(i, j)``: points of scan ``j`` (source) measured against the surface of scan ``i`` (target)."""

    def __init__(self, i: int, j: int) -> None:
        self.i, self.j = i, j

    def matched(self, scans: Sequence[JointScan], rel: np.ndarray, x: np.ndarray, found: Association) -> _Match:
        """The correspondences ``found`` (source points, indices in scan j, and their nearest target points, in
        scan i), the source points placed in S_i at ``x`` by ``rel`` (``T_S_i_S_j``): those whose normals agree."""
        source, target = found.source, found.target
        n, cosine = self._normals(scans, rel, source, target)
        same = np.abs(cosine) >= MIN_NORMAL_COSINE  # not across a crease
        x, n, source, target = x[same], n[same], source[same], target[same]
        q = scans[self.i].points_S[target]
        r = _row_dots(x - q, n)
        variance = ray_variances(n, x - rel[:3, 3], q, scans[self.j].counts_at(source), scans[self.i].counts_at(target))
        return _Match(source, target, r, variance, np.full(len(r), 2, np.uint16), rel,   # one pair alone: share 1
                      found if found.reach_mm else None)

    def at(self, scans: Sequence[JointScan], poses: np.ndarray, m: _Match) -> _Match:
        """The same correspondences ``m`` at ``poses``: their residuals anew (:meth:`residuals`)."""
        return dataclasses.replace(m, residual=self.residuals(scans, poses, m)[0])

    def residuals(self, scans: Sequence[JointScan], poses: np.ndarray, m: _Match) -> tuple[np.ndarray, np.ndarray]:
        """The residuals (mm) of the correspondences ``m`` at ``poses`` and their symmetric normals (S_i): the source
        points placed in S_i, the normals found anew."""
        rel = invert(poses[self.i]) @ poses[self.j]
        x = transform_points(rel, scans[self.j].points_S[m.source])
        n, _ = self._normals(scans, rel, m.source, m.target)
        return _row_dots(x - scans[self.i].points_S[m.target], n), n

    def _normals(self, scans: Sequence[JointScan], rel: np.ndarray, source: np.ndarray, target: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        """:func:`symmetric_normals` (S_i) of the source points ``source`` of scan j placed by ``rel`` against their
        targets ``target`` in scan i."""
        return symmetric_normals(scans[self.i].normals_S[target], rotate_vectors(rel, scans[self.j].normals_S[source]))

    def normal_equations(self, scans: Sequence[JointScan], poses: np.ndarray, origins: np.ndarray, m: _Match,
                         weights: np.ndarray, huber: np.ndarray, normals: np.ndarray | None = None
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(H, b, N)`` (12x12, 12, 12x12) of the weighted residuals in ``(e_j, e_i)`` linearised at the current
        poses: ``H delta = -b`` the normal equations with ``weights``, ``N`` the rows' normal matrix with the
        weights times their Huber factors ``huber`` (the noise's share of the estimate's covariance,
        :func:`_data_system`; only the rows the Huber weights cut differ from ``H``). Worked in S_i: with ``R`` its
        rotation, a world row ``[R n, R ((p - o) x n)]`` is the local row ``[n, (p - o) x n]`` turned by
        ``blockdiag(R, R)``; the symmetric normals ``n`` at ``poses`` are ``normals`` where the caller has them
        (:meth:`residuals`), else found here as :meth:`residuals` finds them."""
        Pi = poses[self.i]
        to_local = invert(Pi)
        rel = to_local @ poses[self.j]
        n = self._normals(scans, rel, m.source, m.target)[0] if normals is None else normals
        q = scans[self.i].points_S[m.target]
        o_j, o_i = (transform_points(to_local, origins[k][None])[0] for k in (self.j, self.i))
        # a row is [n, a, -n, c]: its nine distinct columns K = [n, a, c] are summed, the twelve follow by sign
        K = np.empty((len(n), 9))
        K[:, :3] = n
        x = transform_points(rel, scans[self.j].points_S[m.source])   # as :meth:`residuals` placed them
        _cross(x - o_j, n, K[:, 3:6])
        _cross(n, q - o_i, K[:, 6:])
        Kw = K * weights[:, None]
        KwK = Kw.T @ K
        cut = np.flatnonzero(huber < 1.0)
        KnK = KwK - (Kw[cut] * (1.0 - huber[cut, None])).T @ K[cut]
        B = _rows_to_world(Pi[:3, :3])
        return B @ KwK @ B.T, B @ (Kw.T @ m.residual), B @ KnK @ B.T


#: one pair's correspondences as the refinement holds them: the pair, the handle of its matches on the compute
#: backend (:class:`_PairWork`; on this process's threads the :class:`_Match` itself) and how many they are
_Held = tuple[_Pair, Any, int]


@dataclass(frozen=True)
class _PairPoses:
    """A pair's unit: the pair, its two scans' current poses ``T_W_S`` by scan (mm) and, where the unit needs them,
    their origins in W (mm); only these two, not every scan's, travel with a unit."""

    pair: _Pair
    poses: dict[int, np.ndarray]
    origins: dict[int, np.ndarray] | None = None

    @classmethod
    def of(cls, pair: _Pair, poses: np.ndarray, origins: np.ndarray | None = None) -> _PairPoses:
        """The unit of ``pair`` at every scan's ``poses`` (and ``origins``)."""
        ends = (pair.i, pair.j)
        return cls(pair, {k: poses[k] for k in ends}, None if origins is None else {k: origins[k] for k in ends})

    def scans(self, target: JointScan | StoredJointScan, source: JointScan | StoredJointScan
              ) -> dict[int, JointScan]:
        """The pair's two scans by index, as :class:`_Pair` takes them (a stored one read, :func:`loaded_scan`)."""
        return {self.pair.i: loaded_scan(target), self.pair.j: loaded_scan(source)}


class _PairWork:
    """The refinement's per-pair work as units on a compute backend (``pipeline.compute``): the scans (``scans``, the
    backend's handles of them) and each pair's matches stay where they were made (on a Dask cluster, its workers);
    this process gets the matches' sizes, the residuals and each pair's normal equations. ``run`` names the
    refinement (its scans, priors, pairs, start poses and settings) in each unit's key, and the stages are
    numbered in the order they run, so the same refinement names its units alike."""

    def __init__(self, backend: ComputeBackend, scans: Sequence[Any], run: str) -> None:
        self.backend, self.scans, self.run, self.stages = backend, list(scans), run, 0

    @classmethod
    def of(cls, backend: ComputeBackend, scans: Sequence[Any], model: _Model, pairs: Sequence[tuple[int, int]],
           start_poses: Sequence[np.ndarray], settings: JointSettings,
           associations: Mapping[tuple[int, int], Association]) -> _PairWork:
        """The work of one refinement on ``backend``, its ``run`` a digest of everything its units depend on (the
        scans by their handles' keys where they have them: a Dask future's)."""
        if isinstance(backend, LocalBackend):    # the keys name nothing here
            return cls(backend, scans, "")
        h = hashlib.blake2b(digest_size=16)
        h.update(repr([getattr(s, "key", id(s)) for s in scans]).encode())
        # the sparse matrices by their CSR arrays: made dense they would be (6n)^2 floats each to pickle and hash
        csr = [(M.shape, M.indptr, M.indices, M.data) for M in (model.prior_information, model.A)]
        h.update(pickle.dumps((model.P0, csr, list(pairs), np.stack([np.asarray(T, float) for T in start_poses]),
                               settings)))
        for pair in sorted(associations):
            h.update(np.asarray(pair, np.int64).tobytes())
            h.update(associations[pair].source.tobytes())
            h.update(associations[pair].target.tobytes())
        return cls(backend, scans, h.hexdigest())

    def _keys(self, stage: str, count: int) -> list[str]:
        self.stages += 1
        return [f"joint-{stage}-{self.run}-{self.stages}-{k}" for k in range(count)]

    def keep(self, stage: str, fn: Callable[..., Any], units: Sequence[Any], inputs: Sequence[Sequence[Any]]
             ) -> list:
        """``fn(unit, *inputs)`` of every unit, its results left where they were computed (their handles)."""
        return self.backend.keep(fn, units, self._keys(stage, len(units)), inputs)

    def map(self, stage: str, fn: Callable[..., Any], units: Sequence[Any], inputs: Sequence[Sequence[Any]]
            ) -> list:
        """``fn(unit, *inputs)`` of every unit, its results here."""
        return self.backend.map(fn, units, self._keys(stage, len(units)), inputs)


def _rows_to_world(R: np.ndarray) -> np.ndarray:
    """(12, 9) ``B``: a residual's row in ``(e_j, e_i)``, world axes, from its nine distinct local columns ``[n, a,
    c]`` (:meth:`_Pair.normal_equations`; the row is ``[n, a, -n, c]``, each 3-block turned by the rotation ``R`` of
    S_i)."""
    B = np.zeros((12, 9))
    B[:3, :3] = B[3:6, 3:6] = B[9:, 6:] = R
    B[6:9, :3] = -R
    return B


def symmetric_normals(target_n: np.ndarray, source_n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The residual's direction for point pairs with unit normals ``target_n`` and ``source_n`` (m, 3, one frame):
    the mean of the two, the source's turned to agree with the target's, unit length; and the cosine between
    the two (a correspondence counts where ``|cosine| >= MIN_NORMAL_COSINE``)."""
    cosine = _row_dots(source_n, target_n)
    n = target_n + np.where(cosine < 0.0, -1.0, 1.0)[:, None] * source_n
    n /= np.maximum(np.sqrt(_row_dots(n, n)), 1e-12)[:, None]   # np.linalg.norm's row sums are slower
    return n, cosine


def ray_variances(normals: np.ndarray, source_rays: np.ndarray, target_rays: np.ndarray,
                  source_counts: np.ndarray | None = None, target_counts: np.ndarray | None = None) -> np.ndarray:
    """The variance of point-to-plane residuals along unit ``normals`` between points whose rays from the scanner
    origin are ``source_rays`` and ``target_rays`` (any length, the frame of the normals), relative to two points
    seen head-on: ``(c_p^2 / n_p + c_q^2 / n_q) / 2`` with ``c = n . ray / |ray|`` and ``n`` the points each
    averages (``*_counts``, None: one), at least ``MIN_RAY_COSINES_SQ (1 / n_p + 1 / n_q) / 4``."""
    def cos_sq(rays: np.ndarray) -> np.ndarray:
        return _row_dots(normals, rays) ** 2 / np.maximum(_row_dots(rays, rays), 1e-300)

    inv_p = 1.0 if source_counts is None else 1.0 / source_counts
    inv_q = 1.0 if target_counts is None else 1.0 / target_counts
    floor = MIN_RAY_COSINES_SQ * (inv_p + inv_q) / 2.0
    return np.maximum(cos_sq(source_rays) * inv_p + cos_sq(target_rays) * inv_q, floor) / 2.0


def noise_shares(covering: np.ndarray) -> np.ndarray:
    """The share of its information each residual keeps where ``covering`` scans cover its place (its own and
    every other there): ``2 / k``, at most 1. Where ``k`` scans cover one place, its ``k (k - 1) / 2`` pairs share
    each scan's noise: the surface there is unknown, and eliminating its height leaves ``(I - 1 1^T / k) /
    sigma^2`` of information on the scans' offsets, which the pairs' residuals give at ``2 / k`` of their weight
    each (exact for two scans; counting each at full weight counts every point's noise once per partner).
    docs/correction.md, "Shared noise and the scanner's rays"."""
    return 2.0 / np.maximum(covering, 2.0)


def _covered(_: _Pair, m: _Match) -> tuple[np.ndarray, np.ndarray]:
    """A unit of :func:`_with_shares`: the points a pair's correspondences ``m`` cover in its source scan and in its
    target scan (indices, each once, ascending: a source point has one correspondence, a target point may have
    several; the target's by a count of each index, ``np.unique``'s result without its sort: a quarter of its time on
    the whole part's pairs of 4,500 correspondences in 26,000 target points)."""
    return m.source, np.flatnonzero(np.bincount(m.target)).astype(m.target.dtype)


def _covering(sources: Sequence[bool], scan: JointScan | StoredJointScan,
              *covered: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """How many scans cover each point of ``scan`` (its own and every other it has a correspondence with; uint16):
    one, and one more for each of its pairs (in pair order) whose correspondences cover the point (``covered``,
    :func:`_covered`), as their source scan or their target scan (``sources``; a unit of :func:`_with_shares`)."""
    count = np.ones(len(loaded_scan(scan).points_S), np.uint16)
    for source, (in_source, in_target) in zip(sources, covered, strict=True):
        count[in_source if source else in_target] += 1
    return count


def _shared(_: _Pair, m: _Match, covered_i: np.ndarray, covered_j: np.ndarray) -> _Match:
    """``m`` with its covering count: the larger of its source's and its target's (:func:`_covering`)."""
    return dataclasses.replace(m, covering=np.maximum(covered_j[m.source], covered_i[m.target]))


def _with_shares(work: _PairWork, associated: list[_Held]) -> list[_Held]:
    """``associated`` with each correspondence's :func:`noise_shares`, ``k`` the larger of its source's and its
    target's count of scans (its own and every other it has a correspondence with), counted a scan a unit from the
    points each pair covers (:func:`_covered`: the matches stay where they are)."""
    covers = work.keep("covered", _covered, [p for p, _, _ in associated], [(m,) for _, m, _ in associated])
    roles: dict[int, list[tuple[bool, object]]] = {}
    for (p, _, _), c in zip(associated, covers, strict=True):
        roles.setdefault(p.j, []).append((True, c))
        roles.setdefault(p.i, []).append((False, c))
    scans = sorted(roles)
    covered = dict(zip(scans, work.keep("covering", _covering, [[r for r, _ in roles[k]] for k in scans],
                                        [(work.scans[k], *(c for _, c in roles[k])) for k in scans]), strict=True))
    shared = work.keep("shared", _shared, [p for p, _, _ in associated],
                       [(m, covered[p.i], covered[p.j]) for p, m, _ in associated])
    return [(p, m, size) for (p, _, size), m in zip(associated, shared, strict=True)]


def _huber(r: np.ndarray, threshold_mm: float) -> np.ndarray:
    """The Huber factor (0-1) of each residual ``r`` (mm) at ``threshold_mm``."""
    a = np.abs(r)
    return np.where(a <= threshold_mm, 1.0, threshold_mm / np.maximum(a, 1e-300))


def _refined(u: _PairPoses, m: _Match, target: JointScan, source: JointScan) -> _Match:
    """A unit of :func:`_residuals_at`: ``m`` at the pair's poses (:meth:`_Pair.at`) with its normal equations ``(K,
    g)`` there, each residual weighted by its relative variance alone (``_Match.unit_system``), from the same
    symmetric normals as its residuals (found once, the same bits as found again)."""
    scans = u.scans(target, source)
    residual, normals = u.pair.residuals(scans, u.poses, m)
    m = dataclasses.replace(m, residual=residual)
    K, g, _ = u.pair.normal_equations(scans, u.poses, u.origins, m, 1.0 / m.variance, np.ones(len(residual)),
                                      normals)
    return dataclasses.replace(m, unit_system=(K, g))


def _unit_system(_: _Pair, m: _Match) -> tuple[np.ndarray, np.ndarray]:
    """A unit of :func:`_residuals_at`: the pair's normal equations at its refined poses (:func:`_refined`)."""
    return m.unit_system


def _residuals_at(work: _PairWork, poses: np.ndarray, origins: np.ndarray, associated: Sequence[_Held]
                  ) -> tuple[_Scales, list[tuple[np.ndarray, np.ndarray]]]:
    """The scales of the residuals of the correspondences ``associated`` at ``poses`` (:func:`_scales`) and per pair
    the normal equations ``(K, g)`` (12x12 and 12 in ``(e_j, e_i)``) of its residuals each weighted by its relative
    variance alone (a sigma of 1 mm, no Huber cut), which :func:`_dispersions` scales by the noise's sigma
    (``origins``: the scans' origins in W, mm)."""
    units = [_PairPoses.of(p, poses, origins) for p, _, _ in associated]
    refined = work.keep("refined", _refined, units,
                        [(m, work.scans[p.i], work.scans[p.j]) for p, m, _ in associated])
    held = [(p, m, size) for (p, _, size), m in zip(associated, refined, strict=True)]
    systems = work.map("unit-system", _unit_system, [p for p, _, _ in held], [(m,) for _, m, _ in held])
    return _scales(work, held), systems


#: pairs a unit of :func:`_scales` takes (a unit a pair would cost a Dask task each, about a millisecond)
_SCALE_BATCH = 64
#: a round of :func:`_order_statistics` counts the values in at most this many bins of its bracket (bins of a
#: power of two of the floats' bit patterns, which order non-negative floats as their values)
_SCALE_BINS = 1 << 16
#: the values within a bracket are fetched once there are at most this many (2 MB: after the first round on the
#: whole part's 10.9 M, whose bins are 1/32 of a binade, so that one round and the fetch see every residual twice)
_SCALE_FETCH = 1 << 18
#: a bracket is bit patterns ``[low, low + span)``; the first holds every non-negative float
_ALL_FLOATS = (0, 1 << 63)


@dataclass(frozen=True)
class _Scales:
    """The residuals' count, RMS (mm) and robust scales (1.4826 x their median absolute value, at least
    ``_MIN_SIGMA_MM``; 1 mm where there are none), as they are and whitened by :func:`_whitened`, found where the
    matches are (:func:`_scales`)."""

    count: int
    rms_mm: float
    sigma_mm: float
    whitened_sigma_mm: float


def _absolute_bits(matches: Sequence[_Match], whitened: bool) -> np.ndarray:
    """The bit patterns (int64) of the absolute residuals of ``matches``, whitened (:func:`_whitened`) or as they
    are: ordered as their values."""
    return np.abs(_whitened(matches) if whitened else np.concatenate([m.residual for m in matches])).view(np.int64)


def _shift(span: int) -> int:
    """The bin width (a power of two, its exponent) that splits a bracket of ``span`` bit patterns into at most
    ``_SCALE_BINS`` bins."""
    return max(0, (span - 1).bit_length() - (_SCALE_BINS - 1).bit_length())


def _bracket_counts(queries: tuple[tuple[bool, int, int], ...], squares: bool, *matches: _Match
                    ) -> tuple[list[float], list[tuple[int, np.ndarray]]]:
    """A unit of :func:`_order_statistics`: per query ``(whitened, low, span)`` how many absolute residuals of the
    batch lie in each bin of the bracket (:func:`_shift`), from the first bin that holds any (its index, the counts
    from it to the last that holds any); with ``squares`` also each pair's sum of squared residuals
    (:func:`_scales`)."""
    sums = [float(np.einsum("i,i->", m.residual, m.residual)) for m in matches] if squares else []   # no BLAS
    bits = {w: _absolute_bits(matches, w) for w in {w for w, _, _ in queries}}
    out = []
    for whitened, low, span in queries:
        b = bits[whitened] - low
        at = b[(b >= 0) & (b < min(span, (1 << 63) - 1))] >> _shift(span)
        first = int(at.min()) if len(at) else 0
        out.append((first, np.bincount(at - first)))
    return sums, out


def _bracketed(queries: tuple[tuple[bool, int, int], ...], *matches: _Match) -> list[np.ndarray]:
    """A unit of :func:`_order_statistics`: per query ``(whitened, low, span)`` the batch's absolute residuals in
    the bracket, as floats."""
    bits = {w: _absolute_bits(matches, w) for w in {w for w, _, _ in queries}}
    return [bits[w][(bits[w] >= low) & (bits[w] - low < span)].view(np.float64) for w, low, span in queries]


def _order_statistics(work: _PairWork, batches: Sequence[tuple], targets: Sequence[tuple[bool, int]]
                      ) -> tuple[list[float], list[float]]:
    """The exact value of rank ``r`` (0: the least) among all absolute residuals (whitened or as they are) for each
    target ``(whitened, r)``, found on the backend where the matches are (``batches``: their handles, a unit each):
    each round counts every target's bracket's values by bins of their bit patterns and keeps the bin that holds
    its rank, until it holds at most ``_SCALE_FETCH`` values (fetched, sorted) or one float. Returns the values
    and, from the first round, each pair's sum of squared residuals."""
    brackets = [[*_ALL_FLOATS, 0] for _ in targets]   # low, span (bit patterns), values below low
    open_, fetch, sums = list(range(len(targets))), [], None
    while open_:
        asked = [(targets[t][0], *brackets[t][:2]) for t in open_]
        queries = tuple(dict.fromkeys(asked))           # the two middle ranks share their brackets at first
        got = work.map("bracket", _bracket_counts, [queries] * len(batches), [(sums is None, *b) for b in batches])
        if sums is None:
            sums = [x for batch_sums, _ in got for x in batch_sums]
        still = []
        for q, t in zip((queries.index(a) for a in asked), open_, strict=True):
            low, span, below = brackets[t]
            shift = _shift(span)
            c = np.zeros(-(-span >> shift), np.int64)
            for _, counts in got:
                first, binned = counts[q]
                c[first:first + len(binned)] += binned
            cumulative = below + np.cumsum(c)
            k = int(np.searchsorted(cumulative, targets[t][1], side="right"))
            brackets[t] = [low + (k << shift), min(1 << shift, span - (k << shift)), int(cumulative[k] - c[k])]
            if brackets[t][1] > 1:                           # else one float: it is the value
                (fetch if c[k] <= _SCALE_FETCH else still).append(t)
        open_ = still
    out = [float(np.int64(low).view(np.float64)) for low, _, _ in brackets]
    if fetch:
        queries = tuple((targets[t][0], *brackets[t][:2]) for t in fetch)
        found = [np.sort(np.concatenate(v)) for v in zip(*work.map("bracketed", _bracketed,
                                                                    [queries] * len(batches), batches), strict=True)]
        for t, values in zip(fetch, found, strict=True):
            out[t] = float(values[targets[t][1] - brackets[t][2]])
    return out, sums


def _scales(work: _PairWork, held: Sequence[_Held]) -> _Scales:
    """The count, RMS (mm) and robust scales (:class:`_Scales`) of every residual of ``held`` together (the medians
    exact: the values a partition of all of them would give), found where the matches are: this process gets per
    pair a sum of squares and per round a few counts, never the residuals (10.9 M on the whole part)."""
    n = sum(size for _, _, size in held)
    if not n:
        return _Scales(0, float("nan"), 1.0, 1.0)
    batches = [tuple(m for _, m, _ in held[k:k + _SCALE_BATCH]) for k in range(0, len(held), _SCALE_BATCH)]
    ranks = [n // 2 - 1, n // 2] if n % 2 == 0 else [n // 2]
    values, sums = _order_statistics(work, batches, [(w, r) for w in (False, True) for r in ranks])
    per = len(ranks)
    medians = [0.5 * (v[0] + v[1]) if per == 2 else v[0] for v in (values[:per], values[per:])]
    return _Scales(n, float(np.sqrt(math.fsum(sums) / n)),
                   *(max(1.4826 * float(m), _MIN_SIGMA_MM) for m in medians))


def _whitened(matches: Sequence[_Match]) -> np.ndarray:
    """Every residual of ``matches`` over the square root of its relative variance (:func:`ray_variances`): the
    residuals as if between two single points seen head-on, whose robust scale is the weights' sigma. The
    residuals as they are have a smaller scale (whole part at the simulator's truth: 0.054 mm, their median
    relative variance 0.61), and taken as the sigma it weighed the data 1.75 times too much against the priors;
    whitened they give 0.0711 mm, the simulator's 0.05 mm per point times sqrt(2) (docs/correction.md, "What
    the measurements showed")."""
    return np.concatenate([m.residual / np.sqrt(m.variance) for m in matches]) if matches else np.zeros(0)


def _information(m: _Match, huber: np.ndarray, sigma: float) -> np.ndarray:
    """The weight (1/mm^2) of each residual of ``m``: its Huber factor ``huber`` (:func:`_huber`, on the residual as
    it is: away from the truth the residuals that stand out are the start's errors along the normal, not the rays'
    noise) over ``sigma^2`` and its relative variance (:func:`ray_variances`), times its share
    (:func:`noise_shares`)."""
    return huber / sigma**2 / m.variance * m.share


#: a search for a pair's nearest neighbours (:func:`associate`) looks this many times the distance asked for
#: around each source point, for its nearest and second-nearest target points: from them a later search at poses
#: that moved the pair's points a little searches again only the points whose nearest neighbour may have changed
#: (:func:`_nearest_again`; the whole part's second linearisation, the pairs moved about 0.1 mm: ~15 % of them)
REACH = 1.25
#: mm added to a pair's largest move where it bounds the change of a distance (its rounding is ~1e-13 mm)
_SLACK_MM = 1e-6


@dataclass(frozen=True)
class Association:
    """The nearest neighbours of a scan pair ``(i, j)`` at its start poses: the indices ``source`` of the points of
    scan ``j`` that have a point of scan ``i`` within the distance asked for, and the indices ``target`` of those
    points (int32; before the normal gate of :func:`refine_jointly`, which keeps those whose normals agree).
    Where the search looked ``reach_mm`` around each point (:data:`REACH`; 0: it did not), ``gap_mm`` is for each
    found point at most the distance from its nearest to its second-nearest target point (or to ``reach_mm``), and
    ``near`` are the other source points with a target point within ``reach_mm``, ``near_mm`` at most that
    distance (float32, rounded down; mm): what a later search at poses moved a little needs
    (:func:`_nearest_again`)."""

    source: np.ndarray
    target: np.ndarray
    gap_mm: np.ndarray | None = None
    near: np.ndarray | None = None
    near_mm: np.ndarray | None = None
    reach_mm: float = 0.0


def _rounded_down(values: np.ndarray) -> np.ndarray:
    """``values`` (float64) as float32 no larger than each."""
    f = values.astype(np.float32)
    return np.where(f > values, np.nextafter(f, np.float32(-np.inf)), f)


def joint_tree(scan: JointScan) -> cKDTree:
    """The KD-tree of a scan's points (S, mm) that :func:`associate` searches: split at the middle of each box, not
    at the median (``balanced_tree=False``: built in 0.6 of the time on the whole part's 2 mm scans, queried as fast,
    the same nearest neighbours)."""
    return cKDTree(scan.points_S, balanced_tree=False)


def associate(target: JointScan, tree: cKDTree, source: JointScan, T_S_i_S_j: np.ndarray, max_mm: float
              ) -> Association:
    """Each point of ``source`` (scan j) placed in the target's frame S_i by ``T_S_i_S_j`` and its nearest point of
    ``target`` (scan i, whose points ``tree`` holds) within ``max_mm`` (mm); only the source points inside the
    target's bounding box widened by ``max_mm`` are searched. This is the costly part of the refinement's
    association (a KD-tree query a point), so a job finds it for each pair while it measures, at the tracker
    poses (``online_pairs.OnlinePairs``)."""
    return _nearest(target, tree, source, T_S_i_S_j, max_mm)[0]


def _nearest(target: JointScan, tree: cKDTree, source: JointScan, T_S_i_S_j: np.ndarray, max_mm: float
             ) -> tuple[Association, np.ndarray]:
    """:func:`associate`, and the found source points placed in S_i (mm; the rows of ``T_S_i_S_j`` applied to each
    point, as ``transform_points`` gives them). The target's bounding box is the tree's own (``cKDTree.mins`` and
    ``maxes``: its points' least and largest coordinates), not found again for every pair. Each point is searched
    :data:`REACH` times ``max_mm`` around for its two nearest target points (:class:`Association`'s ``gap_mm`` and
    ``near``; the nearest within ``max_mm`` is the one a search within ``max_mm`` finds)."""
    if not len(target.points_S) or not len(source.points_S):
        return Association(np.zeros(0, np.int32), np.zeros(0, np.int32)), np.zeros((0, 3))
    reach = REACH * max_mm
    low, high = tree.mins - reach, tree.maxes + reach
    x = transform_points(T_S_i_S_j, source.points_S)
    c0, c1, c2 = x[:, 0], x[:, 1], x[:, 2]      # six comparisons of columns: a third of np.all over the rows' time
    inside = np.flatnonzero((c0 >= low[0]) & (c0 <= high[0]) & (c1 >= low[1]) & (c1 <= high[1])
                            & (c2 >= low[2]) & (c2 <= high[2]))
    x = x[inside]
    d, idx = tree.query(x, k=2, distance_upper_bound=reach, workers=1)
    first = d[:, 0]
    found = first < max_mm
    near = (first >= max_mm) & (first < reach)
    gap = np.minimum(d[found, 1], reach) - first[found]     # the second within reach, else reach: a lower bound
    return Association(inside[found].astype(np.int32), idx[found, 0].astype(np.int32), _rounded_down(gap),
                       inside[near].astype(np.int32), _rounded_down(first[near]), reach), x[found]


def _nearest_again(target: JointScan, tree: cKDTree, source: JointScan, T_S_i_S_j: np.ndarray, max_mm: float,
                   before: Association, before_at: np.ndarray) -> tuple[Association, np.ndarray] | None:
    """:func:`_nearest` at the relative pose ``T_S_i_S_j`` of a pair whose search ``before`` (with its reach, found
    at the relative pose ``before_at``) knows every point that may have a target point within ``max_mm`` now: the
    same neighbours (without a reach: a later search looks at every point again). A found point that moved by
    ``delta`` (``(T - T_before) p``) and whose second-nearest target point was more than ``2 delta`` farther than its
    nearest keeps that one (the triangle inequality), a near one farther than ``max_mm + delta`` stays beyond
    ``max_mm``, and a point neither found nor near
    (:class:`Association`) stays beyond it as long as every source point moved less than the reach's margin (told
    from the corners of their box, :func:`_box_corners`); the rest are searched (on the whole part's second
    linearisation about 15 % of the points). None where a point may have moved more: the pair is searched whole
    (:func:`_nearest`)."""
    D = T_S_i_S_j - before_at
    # a point neither found nor near may lie away from those that were and move more than any of them: the margin
    # bounds every source point's move, not the candidates' alone; a move |D p| is convex in p, so its largest over
    # the points is at most its largest over the corners of their box (eight products, not one a point)
    if _farthest_move_mm(D, _box_corners(source.points_S)) + _SLACK_MM >= before.reach_mm - max_mm:
        return None
    candidates = np.concatenate([before.source, before.near])
    points = source.points_S[candidates]
    moved = transform_points(D, points)
    delta = np.sqrt(_row_dots(moved, moved)) + _SLACK_MM      # each point's own move: the bound of its distances'
    x = transform_points(T_S_i_S_j, points)          # each row as :func:`_nearest` places it, the same bits
    held = len(before.source)
    keeps = np.zeros(len(candidates), bool)
    keeps[:held] = before.gap_mm > 2.0 * delta[:held]
    ask = ~keeps
    ask[held:] = before.near_mm < max_mm + delta[held:]
    nearest = np.full(len(candidates), -1, np.int64)
    kept = np.flatnonzero(keeps)
    d = x[kept] - target.points_S[before.target[kept]]
    within = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2] < max_mm * max_mm
    nearest[kept[within]] = before.target[kept[within]]
    asked = np.flatnonzero(ask)
    dist, idx = tree.query(x[asked], distance_upper_bound=max_mm, workers=1)
    nearest[asked[np.isfinite(dist)]] = idx[np.isfinite(dist)]
    order = np.argsort(candidates, kind="stable")      # as the source points are numbered, as :func:`_nearest`
    order = order[nearest[order] >= 0]
    return Association(candidates[order].astype(np.int32), nearest[order].astype(np.int32)), x[order]


def _tree(_: int, scan: JointScan) -> cKDTree:
    """:func:`joint_tree` as a unit of :func:`_associate` (a scan held on the backend, not a stored one)."""
    return joint_tree(scan)


def _near(u: _PairPoses, target: JointScan, source: JointScan, tree: cKDTree | None, given: Association | None,
          before: tuple[Association, np.ndarray] | None, max_mm: float) -> _Match | None:
    """A unit of :func:`_associate`: the pair's correspondences at its poses (None where it has none): ``given``, or
    searched, from the pair's last search where ``before`` has it and the relative pose it was made at
    (:func:`_nearest_again`); a stored target's KD-tree (``tree`` None) built here."""
    if tree is None and given is None:
        tree = _stored_tree(target)
    p, scans = u.pair, u.scans(target, source)
    target, source = scans[p.i], scans[p.j]
    rel = invert(u.poses[p.i]) @ u.poses[p.j]
    if given is not None:
        x = transform_points(rel, source.points_S[given.source])
    else:
        again = None if before is None else _nearest_again(target, tree, source, rel, max_mm, *before)
        given, x = again or _nearest(target, tree, source, rel, max_mm)
    return p.matched(scans, rel, x, given) if len(given.source) else None


def _last_search(_: _Pair, m: _Match) -> tuple[Association, np.ndarray] | None:
    """A unit of :func:`_reassociated`: the search a pair's matches ``m`` came from and the relative pose it was
    made at, where a later one can start from it (``_Match.found``), else None."""
    return None if m.found is None else (m.found, m.found_at)


def _size(_: _Pair, m: _Match | None) -> int:
    """How many correspondences ``m`` holds (-1: None)."""
    return -1 if m is None else len(m.source)


def _associate(work: _PairWork, poses: np.ndarray, pairs: Sequence[tuple[int, int]], max_mm: float,
               given: Mapping[tuple[int, int], Association], trees: dict[int, object],
               before: Sequence[Any] | None = None) -> list[_Held]:
    """The correspondences of every pair at ``poses``: each source point's nearest target point within ``max_mm``
    (:func:`associate`; taken from ``given`` where the pair is there), where their normals agree; pairs without
    any are left out; their noise shares are those of one pair alone (the caller counts them over all pairs,
    :func:`_with_shares`). ``trees``: the handles of the target scans' KD-trees built so far (those missing are
    added; a stored scan's, :class:`StoredJointScan`, is built in the units that search it instead, a few kept there,
    :data:`RECENT_TREES`: kept as a handle, it would stay on a worker for the whole refinement). ``before``: per pair
    the handle of its last search where a pair has one (:func:`_last_search`, :func:`_nearest_again`)."""
    missing = sorted({i for i, j in pairs if (i, j) not in given and not isinstance(work.scans[i], StoredJointScan)}
                     - trees.keys())
    trees.update(zip(missing, work.keep("tree", _tree, missing, [(work.scans[i],) for i in missing]), strict=True))
    units = [_PairPoses.of(_Pair(i, j), poses) for i, j in pairs]
    before = before or [None] * len(pairs)
    found = work.keep("near", functools.partial(_near, max_mm=max_mm), units,
                      [(work.scans[i], work.scans[j], None if (i, j) in given else trees.get(i), given.get((i, j)),
                        last) for (i, j), last in zip(pairs, before, strict=True)])
    sizes = work.map("size", _size, [u.pair for u in units], [(m,) for m in found])
    return [(u.pair, m, size) for u, m, size in zip(units, found, sizes, strict=True) if size >= 0]


def _moved_beyond(scans: Sequence[JointScan], poses: np.ndarray, p: _Pair, m: _Match, limit_mm: float) -> bool:
    """Whether the source points of ``m`` have moved more than ``limit_mm`` in the target's frame S_i between the
    relative pose they were found at (``m.found_at``) and the one at ``poses``: the largest of their displacements
    (each the difference of the two relative poses applied to the point, ``(T_now - T_then) p``: one product a
    point), tried first on every 64th point (a pair that moved has its answer there, the whole part's nearly all),
    then on all."""
    D = invert(poses[p.i]) @ poses[p.j] - m.found_at
    points = scans[p.j].points_S[m.source]
    return _farthest_move_mm(D, points[::64]) > limit_mm or _farthest_move_mm(D, points) > limit_mm


def _box_corners(points: np.ndarray) -> np.ndarray:
    """The eight corners (8, 3) of the axis-aligned box of ``points`` (n, 3; at least one; ``units.box_mm``: numpy's
    least and largest along the first axis of a scan's (n, 3) points take about ten times longer)."""
    low, high = box_mm(points)
    return np.array([[(low, high)[k][0], (low, high)[m][1], (low, high)[q][2]] for k, m, q in np.ndindex(2, 2, 2)])


def _farthest_move_mm(D: np.ndarray, points: np.ndarray) -> float:
    """The largest displacement (mm) of ``points`` (mm) by the difference ``D`` of two relative poses
    (``(T_now - T_then) p``, one product a point); 0 without points."""
    moved = transform_points(D, points)
    return float(np.sqrt(np.max(_row_dots(moved, moved), initial=0.0)))


def _moved(u: _PairPoses, m: _Match, source: JointScan, limit_mm: float) -> bool:
    """:func:`_moved_beyond` as a unit of :func:`_reassociated`."""
    return _moved_beyond({u.pair.j: loaded_scan(source)}, u.poses, u.pair, m, limit_mm)


def _at(u: _PairPoses, m: _Match, target: JointScan, source: JointScan) -> _Match:
    """:meth:`_Pair.at` as a unit of :func:`_reassociated`."""
    return u.pair.at(u.scans(target, source), u.poses, m)


def _reassociated(work: _PairWork, poses: np.ndarray, associated: list[_Held], settings: JointSettings,
                  trees: dict[int, object]) -> tuple[list[_Held], int]:
    """``associated`` at ``poses``: the pairs whose source points have moved more than ``settings.reassociate_mm``
    since their correspondences were found (:func:`_moved_beyond`) have them found anew (:func:`_associate`), the
    others keep theirs (residuals anew); every share is counted again (:func:`noise_shares`).
    Returns them and the number of pairs associated anew. ``associated`` is emptied before the search, so that
    the matches found anew do not live beside those they replace (10.9 M correspondences on the whole part: about
    0.3 GB a set)."""
    def at(held: Sequence[_Held]) -> list[_Held]:
        moved = work.keep("at", _at, [_PairPoses.of(p, poses) for p, _, _ in held],
                          [(m, work.scans[p.i], work.scans[p.j]) for p, m, _ in held])
        return [(p, m, size) for (p, _, size), m in zip(held, moved, strict=True)]

    if settings.reassociate_mm is None:
        return at(associated), 0
    moved = work.map("moved", functools.partial(_moved, limit_mm=settings.reassociate_mm),
                     [_PairPoses.of(p, poses) for p, _, _ in associated],
                     [(m, work.scans[p.j]) for p, m, _ in associated])
    anew = [(p.i, p.j) for (p, _, _), far in zip(associated, moved, strict=True) if far]
    last = work.keep("last-search", _last_search, [p for (p, _, _), far in zip(associated, moved, strict=True) if far],
                     [(m,) for (_, m, _), far in zip(associated, moved, strict=True) if far])
    kept = [held for held, far in zip(associated, moved, strict=True) if not far]
    total = len(associated)
    associated.clear()
    found = _associate(work, poses, anew, settings.max_distance_mm, {}, trees, last) if anew else []
    log.debug("joint refinement: %d of %d pairs associated anew, %d of them without correspondences now (left out)",
              len(anew), total, len(anew) - len(found))
    return _with_shares(work, at(kept) + found), len(anew)


def refine_jointly(
    scans: Sequence[JointScan], priors: Sequence[ScanPrior], pairs: Sequence[tuple[int, int]],
    start_poses: Sequence[np.ndarray], transfers: Sequence[TransferPrior] = (),
    mount_prior: MountPrior | None = None, settings: JointSettings = JointSettings(),
    associations: Mapping[tuple[int, int], Association] | None = None, backend: ComputeBackend | None = None,
) -> JointResult:
    """Refine every scan pose jointly from ``start_poses`` (the tracker poses: see the module doc) on the overlaps
    of ``pairs`` (``(i, j)``: points of ``j`` measured against the surface of ``i``); the priors are the tracker poses
    ``priors`` (``T_W_S`` and covariance), ``transfers`` and ``mount_prior`` as in ``pose_graph.refine_poses``.
    ``associations``: pairs' nearest neighbours found at the same start poses with ``settings.max_distance_mm``
    (:func:`associate`, while the job measured); the other pairs' are found here.
    The per-pair work (association, residuals, each pair's normal equations) runs as units on ``backend``
    (``pipeline.compute``; this process's threads where None): ``scans`` are its handles of the scans
    (:meth:`ComputeBackend.keep` or ``put``; on this process's threads the scans themselves) and every pair's
    correspondences stay where they were found, so that on a Dask cluster this process holds neither the scans
    nor the correspondences, only each pair's normal equations, the residuals (for their robust scale) and the
    solve (docs/compute.md).

    Nine parameters: the data (scans, pairs, start poses, associations), the settings, the tracker chain's
    three priors taken as ``pose_graph.refine_poses`` and :func:`chain_covariance` take them, and the backend."""
    if not (len(scans) == len(priors) == len(start_poses)):
        raise RefineError(f"{len(scans)} scans, {len(priors)} priors and {len(start_poses)} start poses differ")
    model = _Model(priors, transfers, mount_prior)
    work = _PairWork.of(backend or LocalBackend(), scans, model, pairs, start_poses, settings, associations or {})
    return _refine(work, model, pairs, start_poses, settings, associations or {})


def _refine(work: _PairWork, model: _Model, pairs: Sequence[tuple[int, int]], start_poses: Sequence[np.ndarray],
            settings: JointSettings, associations: Mapping[tuple[int, int], Association]) -> JointResult:
    """:func:`refine_jointly` on the priors' ``model`` with the per-pair ``work``."""
    poses = np.stack([np.asarray(T, float) for T in start_poses])
    e = model.corrections(poses)
    trees: dict[int, object] = {}
    associated = _with_shares(work, _associate(work, poses, pairs, settings.max_distance_mm, associations, trees))
    if settings.reassociate_mm is None:
        trees.clear()                      # nothing is searched again: the KD-trees need not live on
    H_prior = model.prior_information
    rms_before, sigma, H, used, n_corr, it, anew = float("nan"), 1.0, None, 0, 0, 0, 0
    for it in range(1, settings.iterations + 1):
        if it > 1:
            kept = []                      # the last linearisation's matches: freed as they are replaced
            associated, moved = _reassociated(work, poses, associated, settings, trees)
            anew += moved
            if it == settings.iterations:
                trees.clear()              # nothing is searched again
        kept = [held for held in associated if held[2] >= settings.min_correspondences]
        scales = _scales(work, kept)       # where the matches are: this process never holds the residuals
        sigma = settings.sigma_mm or scales.whitened_sigma_mm
        if it == 1:
            rms_before = scales.rms_mm
        huber_mm = settings.huber_k * (settings.sigma_mm or scales.sigma_mm)   # on the residuals as they are
        used, n_corr = len(kept), scales.count
        H, b_e, N = _data_system(model, work, poses, kept, sigma, huber_mm)
        # linearised at e: data term |r + J (A theta - e)|^2, prior |theta|^2_prior -> solve for theta
        rhs = model.A.T @ (H @ e.ravel() - b_e)
        H_theta = (model.A.T @ H @ model.A + H_prior).tocsc()
        theta = splu(H_theta).solve(rhs)
        e_new = (model.A @ theta).reshape(-1, 6)
        step = np.abs(e_new - e)
        move = float(np.max(np.linalg.norm(step[:, :3], axis=1)
                            + settings.lever_mm * np.linalg.norm(step[:, 3:], axis=1)))
        e, poses = e_new, model.poses(e_new)
        log.debug("joint refinement linearisation %d: %d pairs, %d points, sigma %.4f mm, largest move %.2e mm",
                  it, used, n_corr, sigma, move)
        if move < settings.tolerance_mm:
            break
    final, unit_systems = _residuals_at(work, poses, model.origins, kept)
    kept_pairs = [p for p, _, _ in kept]
    kept = associated = []                 # the matches are not needed any more: released (whole part: ~0.3 GB)
    rms_after = final.rms_mm
    noise_sigma = settings.sigma_mm or final.whitened_sigma_mm
    ratio = (noise_sigma / sigma) ** 2
    posterior = _posterior(model, H_theta, H_prior + ratio * (model.A.T @ N.matrix() @ model.A))
    factors, dispersion = _dispersions(model, kept_pairs, unit_systems, noise_sigma, posterior)
    if np.any(factors > 1.0):
        posterior = _posterior(model, H_theta, H_prior + ratio * (model.A.T @ N.matrix(factors) @ model.A))
    mount = None
    if model.L is not None:   # the data's information under their noise at the refined poses, plus the priors
        mount = _mount_estimate(model, (H_theta - H_prior) / ratio + H_prior, posterior, theta)
    prior_cov = model.scan_covariances(model.prior_covariance)
    log.info("joint refinement: %d scans, %d pairs, %d points, %d iterations, %d pairs associated anew; sigma "
             "%.4f mm (%.4f mm at the refined poses), RMS %.4f -> %.4f mm", model.n, used, n_corr, it, anew, sigma,
             noise_sigma, rms_before, rms_after)
    return JointResult([T for T in poses], posterior.scan_covariances(), prior_cov, mount, it, used, n_corr,
                       sigma, rms_before, rms_after, noise_sigma, anew, posterior, dispersion)


def chain_covariance(priors: Sequence[ScanPrior], transfers: Sequence[TransferPrior],
                     mount_prior: MountPrior | None) -> PoseCovariance:
    """The scans' errors as the tracker chain alone gives them (no correction ran): the readings', the transfers'
    and the mount's priors through the joint refinement's error model (the module doc)."""
    model = _Model(priors, transfers, mount_prior)
    return model.pose_covariance(model.prior_information, model.prior_information, "tracker chain prior")


def _posterior(model: _Model, H: sparse.spmatrix, information: sparse.spmatrix) -> PoseCovariance:
    """The posterior of the estimate ``theta`` from the normal matrix ``H`` it was solved with (data ``D`` + prior
    ``P``, the data weighted with a sigma taken at the last linearisation's poses: with one linearisation the
    start's, where the residuals also hold the start's misalignment), and the ``information`` its errors carry
    (``P`` + the data's under their noise at the refined poses, :func:`_data_system`, each pair's counted at its
    group's dispersion, :func:`_dispersions`): the estimate's error is ``-H^-1 (P theta_true + D-weighted
    noise)``, its covariance ``H^-1 information H^-1`` (``H^-1`` where the two agree), kept as the two sparse
    matrices (``PoseCovariance``: the blocks asked for, never the dense (m x m))."""
    return model.pose_covariance(H, information, "joint refinement posterior")


def _dispersions(model: _Model, pairs: Sequence[_Pair], unit_systems: Sequence[tuple[np.ndarray, np.ndarray]],
                 sigma: float, posterior: PoseCovariance) -> tuple[np.ndarray, dict[str, float]]:
    """How much more the pairs' residuals scatter than their points' independent noise (``sigma``, mm, two points
    head-on; :func:`ray_variances`) says, pooled over the pairs of the same two tracker stations: per pair of
    ``pairs`` its group's factor (at least 1), and the factors by group ("2-3").

    A pair's residuals at the refined poses, whitened, projected on the directions a motion of scan j relative
    to scan i moves them (:meth:`_Pair.normal_equations`, rank ``r``, 6 but where the overlap slides) have a
    chi-square of about ``r - tr(K C)`` if its points err independently (``K`` the pair's information in both
    scans' errors, ``C`` their posterior under that noise, ``posterior``'s: what the fit took up; so measured on
    noise alone, whatever the pairs' noise shares, :func:`noise_shares`). An error the pair's points share
    (the thinning's voxel grid, the normals', the correspondences found at misaligned starts) adds to it and is
    not averaged away by the pair's thousands of points, so the group's information is counted at the pooled
    ratio instead (a variance component of the group, docs/correction.md, "Pairs that err together"); never
    below 1, the points' own noise being measured by ``sigma`` already, and 1 where the group's pairs leave less
    than :data:`MIN_REDUNDANCY` of their chi-square to test (a pair that alone places a scan leaves none).
    ``unit_systems``: each pair's normal equations at the refined poses with a sigma of 1 mm
    (:func:`_residuals_at`), scaled here by ``sigma``."""
    if not pairs:
        return np.ones(0), {}
    columns = model.scan_columns

    def test(p: _Pair, unit: tuple[np.ndarray, np.ndarray]) -> tuple[float, float]:
        K, g = unit[0] / sigma**2, unit[1] / sigma**2
        vals, vecs = np.linalg.eigh(K[:6, :6])   # the residuals depend on scan j's motion relative to scan i's
        seen = vals > vals.max() * 1e-9
        q = float(np.sum((vecs[:, seen].T @ g[:6]) ** 2 / vals[seen]))
        (cj, Aj), (ci, Ai) = columns[p.j], columns[p.i]
        cols = np.union1d(cj, ci)
        Ap = np.zeros((12, len(cols)))
        Ap[:6, np.searchsorted(cols, cj)] = Aj
        Ap[6:, np.searchsorted(cols, ci)] = Ai
        return q, float(np.count_nonzero(seen)) - float(np.sum(K * (Ap @ posterior.theta_covariance(cols) @ Ap.T)))

    tests = np.array([test(p, u) for p, u in zip(pairs, unit_systems, strict=True)])
    st = model.stations
    group = np.array([f"{min(st[p.i], st[p.j])}-{max(st[p.i], st[p.j])}" for p in pairs], dtype=object)
    q, free = ({str(g): float(tests[group == g, k].sum()) for g in sorted(set(group))} for k in (0, 1))
    factor = {g: max(1.0, q[g] / free[g]) if free[g] >= MIN_REDUNDANCY else 1.0 for g in q}
    log.debug("joint refinement: pairs' dispersion per pair of tracker stations %s", factor)
    return np.array([factor[g] for g in group]), factor


@dataclass(frozen=True)
class _NoiseBlocks:
    """Each pair's normal matrix (12x12 in ``(e_j, e_i)``, world axes) with its rows' weights times their Huber
    factors once more: the noise's share of the information an estimate weighted by ``H_e`` carries
    (:func:`_data_system`), for the ``n`` scans."""

    pairs: list[_Pair]
    blocks: list[np.ndarray]
    n: int

    def matrix(self, factors: np.ndarray | None = None) -> sparse.csr_matrix:
        """``N_e`` (6n x 6n, sparse): the blocks summed, each times its pair's ``factors`` (None: 1 each)."""
        f = np.ones(len(self.blocks)) if factors is None else factors
        return _assembled(self.n, self.pairs, [k * B for k, B in zip(f, self.blocks, strict=True)])


def _assembled(n: int, pairs: Sequence[_Pair], blocks: Sequence[np.ndarray]) -> sparse.csr_matrix:
    """The 12x12 ``blocks`` of ``pairs`` (in ``(e_j, e_i)``) summed into one sparse 6n x 6n matrix."""
    if not blocks:
        return sparse.csr_matrix((6 * n, 6 * n))
    rows, cols = [], []
    for p in pairs:
        idx = np.r_[np.arange(6) + 6 * p.j, np.arange(6) + 6 * p.i]
        r, c = np.meshgrid(idx, idx, indexing="ij")
        rows.append(r.ravel())
        cols.append(c.ravel())
    values = np.concatenate([B.ravel() for B in blocks])
    return sparse.csr_matrix((values, (np.concatenate(rows), np.concatenate(cols))), shape=(6 * n, 6 * n))


def _system(u: _PairPoses, m: _Match, target: JointScan, source: JointScan, sigma: float, huber_mm: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A unit of :func:`_data_system`: the pair's ``(H, b, N)`` (:meth:`_Pair.normal_equations`)."""
    huber = _huber(m.residual, huber_mm)
    weights = _information(m, huber, sigma)
    return u.pair.normal_equations(u.scans(target, source), u.poses, u.origins, m, weights, huber)


def _data_system(model: _Model, work: _PairWork, poses: np.ndarray, kept: Sequence[_Held], sigma: float,
                 huber_mm: float) -> tuple[sparse.csr_matrix, np.ndarray, _NoiseBlocks]:
    """The data's normal equations in the stacked corrections ``e``, each residual weighted by ``sigma`` (mm, two
    points head-on; :func:`_information`) and Huber-cut beyond ``huber_mm``: sparse ``H_e`` (6n x 6n) and ``b_e``, and
    the blocks of ``N_e``, the normal matrix of the same rows weighted by their Huber factor once more. With the
    residuals' noise ``ratio`` times the variance ``sigma^2`` weighs them by, the noise adds ``ratio N_e`` (not
    ``H_e``) to the information an estimate weighted by ``H_e`` carries (:func:`_posterior`)."""
    n = model.n
    b = np.zeros(6 * n)
    pairs = [p for p, _, _ in kept]
    systems = work.map("system", functools.partial(_system, sigma=sigma, huber_mm=huber_mm),
                       [_PairPoses.of(p, poses, model.origins) for p in pairs],
                       [(m, work.scans[p.i], work.scans[p.j]) for p, m, _ in kept])
    for p, (_, g, _) in zip(pairs, systems, strict=True):
        b[np.r_[np.arange(6) + 6 * p.j, np.arange(6) + 6 * p.i]] += g
    return _assembled(n, pairs, [H for H, _, _ in systems]), b, _NoiseBlocks(pairs, [N for _, _, N in systems], n)


def _mount_estimate(model: _Model, information: sparse.spmatrix, posterior: PoseCovariance, theta: np.ndarray
                    ) -> MountEstimate:
    """The shared mount correction ``D = Exp(L u)``: its posterior (from ``posterior``) and the data's information
    on it (from ``information``, the data's and the priors' on ``theta``, sparse)."""
    L, prior = model.L, np.asarray(model.mount_prior.covariance, float)
    first = model.size - 6
    own_prior = sparse.csr_matrix((np.ones(6), (np.arange(first, model.size), np.arange(first, model.size))),
                                  shape=information.shape)
    data_u = _marginal_information(sparse.csc_matrix(information - own_prior), first)   # without the mount's prior
    ratio, U = np.linalg.eigh(0.5 * (data_u + data_u.T))
    d = L @ theta[-6:]
    cov = L @ posterior.theta_covariance(np.arange(first, model.size)) @ L.T
    Linv = np.linalg.inv(L)
    data_D = Linv.T @ data_u @ Linv
    log.info("joint refinement: mount correction %s mm, %s deg", np.round(d[:3], 4), np.round(np.degrees(d[3:]), 5))
    observed = int(np.sum(ratio >= model.mount_prior.min_information_ratio))   # the rest is the prior's
    return MountEstimate(from_rotvec(d[:3], d[3:]), 0.5 * (cov + cov.T), prior, 0.5 * (data_D + data_D.T),
                         ratio, U, observed)


def _marginal_information(H: sparse.csc_matrix, first: int) -> np.ndarray:
    """The information (dense) of the few unknowns from ``first`` on with the earlier ones marginalised: their
    Schur complement in ``H`` (sparse), the earlier ones' block factored sparse and solved against the few columns."""
    A, B, C = H[:first, :first], H[:first, first:].toarray(), H[first:, first:].toarray()
    return C - B.T @ splu(sparse.csc_matrix(A)).solve(B)
