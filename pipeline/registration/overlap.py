"""Overlap and pair selection (docs/registration.md): the points of two stitched scans whose nearest
neighbour in the other scan is closer than delta, and which scan pairs of a job are worth registering.

Both clouds are in one frame (the world, after the tracker stitch), in millimetres. ``delta`` is either
configured or derived from the pose uncertainty of the pair: a pose error of translation ``dt`` and rotation
``dr`` moves a point at lever arm ``r`` from the rotation centre by at most ``|dt| + |dr| r``.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy import sparse
from scipy.spatial import cKDTree

log = logging.getLogger(__name__)


class OverlapError(ValueError):
    """Bad input to the overlap extraction (shapes, non-finite values, non-positive delta)."""


@dataclass(frozen=True)
class Overlap:
    """Indices of the overlapping points of each cloud and the threshold used (mm)."""

    source_idx: np.ndarray
    target_idx: np.ndarray
    delta_mm: float

    @property
    def size(self) -> int:
        """The smaller of the two overlap point counts."""
        return int(min(len(self.source_idx), len(self.target_idx)))


def _cloud(points: ArrayLike, name: str) -> np.ndarray:
    P = np.asarray(points, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3:
        raise OverlapError(f"{name}: expected an (N, 3) array, got shape {P.shape}")
    if not np.all(np.isfinite(P)):
        raise OverlapError(f"{name}: contains NaN or infinite coordinates")
    return P


def delta_from_covariance(
    covariance: ArrayLike, lever_arm_mm: float, sigmas: float = 3.0, min_delta_mm: float = 1.0
) -> float:
    """Overlap threshold (mm) from the 6x6 covariance of the pair's relative pose error.

    ``covariance`` is ordered (tx, ty, tz in mm^2, rx, ry, rz in rad^2) about the overlap's centre;
    ``lever_arm_mm`` is the largest distance of an overlap point from that centre. The result is
    ``sigmas`` times the 1-sigma worst-direction displacement, never below ``min_delta_mm`` (point spacing
    and scanner noise still separate perfectly placed scans).
    """
    C = np.asarray(covariance, dtype=float)
    if C.shape != (6, 6) or not np.all(np.isfinite(C)):
        raise OverlapError(f"covariance must be a finite 6x6 matrix, got shape {C.shape}")
    if lever_arm_mm < 0 or sigmas <= 0 or min_delta_mm <= 0:
        raise OverlapError("lever_arm_mm must be >= 0, sigmas and min_delta_mm > 0")
    sigma_t = float(np.sqrt(max(np.linalg.eigvalsh(C[:3, :3]).max(), 0.0)))
    sigma_r = float(np.sqrt(max(np.linalg.eigvalsh(C[3:, 3:]).max(), 0.0)))
    return max(sigmas * (sigma_t + sigma_r * lever_arm_mm), min_delta_mm)


def relative_covariance(cov_a: ArrayLike, cov_b: ArrayLike) -> np.ndarray:
    """Covariance of the relative pose of two independently measured poses (first-order: the sum)."""
    return np.asarray(cov_a, dtype=float) + np.asarray(cov_b, dtype=float)


def extract_overlap(source_mm: ArrayLike, target_mm: ArrayLike, delta_mm: float) -> Overlap:
    """Points of each cloud whose nearest neighbour in the other cloud is closer than ``delta_mm``."""
    S = _cloud(source_mm, "source")
    T = _cloud(target_mm, "target")
    if not delta_mm > 0:
        raise OverlapError(f"delta_mm must be > 0, got {delta_mm}")
    if len(S) == 0 or len(T) == 0:
        return Overlap(np.empty(0, int), np.empty(0, int), float(delta_mm))
    ov = overlap_at(S, cKDTree(S), T, cKDTree(T), np.eye(4), delta_mm)
    log.debug("overlap at delta %.3f mm: %d source, %d target points", delta_mm, len(ov.source_idx),
              len(ov.target_idx))
    return ov


def overlap_at(source_mm: np.ndarray, source_tree: cKDTree, target_mm: np.ndarray, target_tree: cKDTree,
               T: np.ndarray, delta_mm: float) -> Overlap:
    """:func:`extract_overlap` of the source moved by ``T`` (4x4 mm) and the target, from KD-trees built once
    per cloud (``source_tree`` of the unmoved source, ``target_tree`` of the target): the target is moved
    into the source's frame for its half, distances being the same in either frame."""
    M = np.asarray(T, float)
    d_s, _ = target_tree.query(source_mm @ M[:3, :3].T + M[:3, 3], k=1, distance_upper_bound=delta_mm)
    d_t, _ = source_tree.query((target_mm - M[:3, 3]) @ M[:3, :3], k=1, distance_upper_bound=delta_mm)
    return Overlap(np.flatnonzero(d_s < delta_mm), np.flatnonzero(d_t < delta_mm), float(delta_mm))


def occupied_cells(points: np.ndarray, cell_mm: float) -> np.ndarray:
    """Sorted unique ids of the ``cell_mm`` grid cells the points (world frame, mm) occupy (one int64 per cell):
    all :func:`shared_cells` needs of a cloud."""
    keys = np.floor(points / cell_mm).astype(np.int64) + (1 << 20)  # non-negative within +-1 km at 1 mm cells
    return np.unique((keys[:, 0] << 42) | (keys[:, 1] << 21) | keys[:, 2])


def _best_partners(shared_row: np.ndarray, stations: np.ndarray, i: int, max_partners: int) -> list[int]:
    """Cloud ``i``'s kept candidates: the ``max_partners`` clouds sharing the most cells with it among its own
    tracker station, and as many among the others (ties: the lower index first)."""
    best: list[int] = []
    for same in (True, False):
        mask = (stations == stations[i]) == same
        partners = np.flatnonzero(mask & (shared_row > 0))
        best.extend(partners[np.argsort(-shared_row[partners], kind="stable")[:max_partners]].tolist())
    return best


def _check_selection(cell_mm: float, max_partners: int) -> None:
    if cell_mm <= 0 or max_partners < 1:
        raise OverlapError(f"cell_mm must be > 0 and max_partners >= 1, got {cell_mm}, {max_partners}")


def shared_cells(cells: Sequence[np.ndarray]) -> np.ndarray:
    """``shared[i, j]``: how many grid cells clouds ``i`` and ``j`` both occupy (0 on the diagonal), from each
    cloud's :func:`occupied_cells`; :func:`overlapping_pairs` selects from it, once or at several ``max_partners``."""
    if not len(cells):
        return np.zeros((0, 0), np.int64)
    _, column = np.unique(np.concatenate(cells), return_inverse=True)
    row = np.repeat(np.arange(len(cells)), [len(c) for c in cells])
    incidence = sparse.csr_matrix((np.ones(len(row), np.int64), (row, column.ravel())))
    shared = (incidence @ incidence.T).toarray()
    np.fill_diagonal(shared, 0)
    return shared


def overlapping_pairs(
    clouds: list[np.ndarray], stations: ArrayLike, cell_mm: float, max_partners: int,
) -> list[tuple[int, int]]:
    """Pairs ``(i, j)``, ``i < j``, of world-frame clouds (mm) worth registering, in index order.

    Two clouds are candidates when they share a cell of the ``cell_mm`` grid. Each cloud keeps its
    ``max_partners`` candidates with the most shared cells among the clouds of its own tracker station, and
    as many among the other stations (the links that carry a coordinate transfer); a pair is kept when either
    of its clouds keeps it (:func:`select_pairs`). On a plan of hundreds of scans this keeps the raster neighbours
    and drops the pairs that only touch at a corner. :class:`PairSelector` finds a superset of these pairs as the
    clouds arrive one by one.
    """
    _check_selection(cell_mm, max_partners)
    cells = [occupied_cells(_cloud(c, f"cloud {i}"), cell_mm) for i, c in enumerate(clouds)]
    return select_pairs(shared_cells(cells), stations, max_partners)


def select_pairs(shared: np.ndarray, stations: ArrayLike, max_partners: int) -> list[tuple[int, int]]:
    """:func:`overlapping_pairs` of clouds whose :func:`shared_cells` are ``shared``: each keeps its ``max_partners``
    candidates sharing the most cells among its own tracker station and as many among the others."""
    if max_partners < 1:
        raise OverlapError(f"max_partners must be >= 1, got {max_partners}")
    stations = np.asarray(stations)
    keep = set()
    for i in range(len(shared)):
        keep.update((min(i, j), max(i, j)) for j in _best_partners(shared[i], stations, i, max_partners))
    return sorted(keep)


class PairSelector:
    """:func:`overlapping_pairs` as the clouds of a job arrive, one at a time
    (docs/pairs-while-measuring.md).

    :meth:`add` returns the earlier clouds that the new one may be paired with in the end: those among its
    kept candidates so far, and those that keep it among theirs so far. A cloud kept among all clouds is kept
    among any subset that holds it (removing competitors never lowers its rank, and ties go by index), so
    every pair :func:`overlapping_pairs` selects over all the clouds was returned when its later cloud
    arrived; a few more may be (pairs a later cloud then displaces), never fewer.
    """

    def __init__(self, cell_mm: float, max_partners: int):
        _check_selection(cell_mm, max_partners)
        self.cell_mm, self.max_partners = float(cell_mm), int(max_partners)
        self._cells: list[np.ndarray] = []
        self._boxes = np.zeros((0, 2, 3), np.int64)  # each cloud's lowest and highest cell along x, y, z
        self._stations: list[int] = []
        self._shared = np.zeros((0, 0), np.int64)

    def __len__(self) -> int:
        return len(self._cells)

    def add(self, cloud_W: np.ndarray, station: int) -> list[int]:
        """Take the next cloud (world frame, mm) of tracker station ``station``; returns its possible partners
        (indices of earlier clouds, ascending)."""
        cloud = _cloud(cloud_W, f"cloud {len(self)}")
        cells = occupied_cells(cloud, self.cell_mm)
        n = len(self._cells)
        box = (np.floor(np.array([cloud.min(axis=0), cloud.max(axis=0)]) / self.cell_mm).astype(np.int64)
               if len(cloud) else np.array([[1, 1, 1], [0, 0, 0]], np.int64))   # an empty box meets none
        row = np.zeros(n, np.int64)
        meets = np.all((self._boxes[:, 0] <= box[1]) & (self._boxes[:, 1] >= box[0]), axis=1)
        for k in np.flatnonzero(meets):  # only clouds whose boxes of cells meet can share a cell
            row[k] = len(np.intersect1d(self._cells[k], cells, assume_unique=True))
        self._boxes = np.concatenate([self._boxes, box[None]])
        shared = np.zeros((n + 1, n + 1), np.int64)
        shared[:n, :n], shared[n, :n], shared[:n, n] = self._shared, row, row
        self._shared, self._cells = shared, [*self._cells, cells]
        self._stations.append(int(station))
        stations = np.asarray(self._stations)
        partners = set(_best_partners(shared[n], stations, n, self.max_partners))
        partners.update(i for i in np.flatnonzero(row > 0).tolist()
                        if n in _best_partners(shared[i], stations, i, self.max_partners))
        return sorted(partners)

    def kept(self, i: int, j: int) -> bool:
        """Whether the pair of clouds ``i`` and ``j`` is still among those :meth:`add` returned: one of them keeps
        the other among its candidates so far. Once not, never again (a later cloud only adds competitors), so a
        pair :func:`overlapping_pairs` selects over all the clouds is kept at every step."""
        stations = np.asarray(self._stations)
        return (j in _best_partners(self._shared[i], stations, i, self.max_partners)
                or i in _best_partners(self._shared[j], stations, j, self.max_partners))
