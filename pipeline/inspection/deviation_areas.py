"""Deviation areas: the connected parts of the measured surface beyond the tolerance band, what a quality
engineer marks on the part (docs/inspection-method.md, "Deviation areas").

Frame F (CAD), millimetres. Each point's deviation is first averaged over its neighbours within
``smoothing_mm`` (scanner noise of 0.05 mm per point would otherwise put a few percent of any surface
outside a +-0.1 mm band); points whose averaged deviation is above the band (upper) or below it (lower) are
linked to such neighbours of the same side within three point spacings (at least ``smoothing_mm``), and
every linked set at least ``min_area_mm2`` large is one area. A point's share of the surface is
``pi d^2 / (k + 1)``, ``d`` midway between its k-th and (k+1)-th neighbour (the disk holds the point and k
neighbours; unbiased on a grid). Per area: the area-weighted centroid, the area, the extreme of the
averaged deviation (a noise peak of one point is no defect) and the mean of the points' own deviations.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from tandemscan.pipeline.geometry.units import box_mm

NEIGHBOURS = 48  # at most this many neighbours enter a point's average
DENSITY_K = 8  # the neighbour whose distance gives a point's share of the surface
_CHUNK = 50_000


@dataclass(frozen=True)
class DeviationArea:
    """One connected area beyond the band: ``side`` "upper" (material above CAD) or "lower"; centroid in
    CAD frame F (mm), area (mm^2), extreme (largest |averaged deviation|, signed) and mean deviation (mm)."""

    id: int
    side: str
    centroid_mm: tuple[float, float, float]
    area_mm2: float
    extreme_mm: float
    mean_mm: float
    points: int
    decision: str = ""  # "nonconforming" or "indeterminate" once decided (``verdict.judge``)
    uncertainty_mm: float | None = None  # expanded U of its extreme, mm
    reason: str = ""


@dataclass(frozen=True)
class LocalDeviation:
    """Per point (frame F): the deviation averaged over ``smoothing_mm`` and the point's surface share; of the
    cloud's points ``at`` (indices) where only those were asked for; ``nearest_mm``, the nearest-neighbour distances
    the point spacing is the median of (of the points asked for, or of a screening's points: :func:`_screened`)."""

    smoothed_mm: np.ndarray
    area_mm2: np.ndarray
    nearest_mm: np.ndarray
    at: np.ndarray | None = None  # indices into the cloud; None: every point

    @property
    def spacing_mm(self) -> float:
        """The median nearest-neighbour distance (mm; 0 without points)."""
        return float(np.median(self.nearest_mm)) if len(self.nearest_mm) else 0.0


def even_centres(points_mm: np.ndarray, cell_mm: float) -> np.ndarray:
    """Indices of one point per occupied cube of side ``cell_mm``, the first of its points, in the order of
    the cubes: an even thinning of a cloud (frame F, mm). The cube keys are formed a chunk at a time."""
    p = np.asarray(points_mm, float)
    if not len(p):
        return np.zeros(0, np.int64)
    p_lo, p_hi = box_mm(p)
    lo = np.floor(p_lo / cell_mm)  # the smallest cube index (floor of a quotient is monotone)
    size = (np.floor(p_hi / cell_mm) - lo + 1).astype(np.int64)
    keys = np.empty(len(p), np.int64)
    for at in range(0, len(p), _CHUNK):
        cell = (np.floor(p[at:at + _CHUNK] / cell_mm) - lo).astype(np.int64)
        keys[at:at + _CHUNK] = (cell[:, 0] * size[1] + cell[:, 1]) * size[2] + cell[:, 2]
    order = np.argsort(keys)
    keys = keys[order]
    return np.minimum.reduceat(order, np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]]))


def kd_tree(points_mm: np.ndarray) -> cKDTree:
    """A KD tree of a cloud for the bounded neighbour queries here: median-free with leaves of 32 points,
    which builds in half the time of the defaults and answers them as fast (whole-part job, 8 M points)."""
    return cKDTree(points_mm, leafsize=32, balanced_tree=False)


class DeviationCloud:
    """A cloud's points and their deviations (frame F, mm, float64) with what its areas are found on: its KD tree
    and, per smoothing radius, its coarse screening (:func:`_screening`), each built on first use and kept by this
    object. The areas at the band and at the verdict's guard band are found on the same object (the inspection's
    result holds it, ``inspect.InspectionResult.deviation_cloud``): they share the tree and the screening, which go
    with it, not with any cache that outlives the inspection."""

    def __init__(self, points_mm: np.ndarray, deviations_mm: np.ndarray):
        self.points_mm = np.asarray(points_mm, dtype=np.float64)
        self.deviations_mm = np.asarray(deviations_mm, dtype=np.float64)
        self._tree: cKDTree | None = None
        self._screenings: dict[float, tuple[np.ndarray, LocalDeviation]] = {}

    @property
    def tree(self) -> cKDTree:
        """The points' KD tree (:func:`kd_tree`), built on first use."""
        if self._tree is None:
            self._tree = kd_tree(self.points_mm)
        return self._tree

    def screening(self, smoothing_mm: float) -> tuple[np.ndarray, LocalDeviation]:
        """:func:`_screening` of the cloud at ``smoothing_mm``, built on first use: the same for every band."""
        if smoothing_mm not in self._screenings:
            self._screenings[smoothing_mm] = _screening(self.points_mm, self.deviations_mm, smoothing_mm, self.tree)
        return self._screenings[smoothing_mm]


def neighbours_within(tree: cKDTree, queries: np.ndarray, k: int, radius_mm: float, need: int
                      ) -> tuple[np.ndarray, np.ndarray]:
    """``tree.query(queries, k)``'s (distances, indices) where they are at most ``radius_mm``, and the
    neighbours up to the ``need``-th (0-based column) for every query however far; the further entries are
    inf (index ``tree.n``). The search stops at the radius (a surface point has about half its 48 nearest
    within 4 mm); only the queries whose ``need``-th neighbour lies beyond it are searched again unbounded."""
    dist, idx = tree.query(queries, k=k, workers=-1, distance_upper_bound=radius_mm * (1.0 + 1e-9))
    dist, idx = dist.reshape(-1, k), idx.reshape(-1, k)
    again = np.flatnonzero(np.isinf(dist[:, need]))
    if len(again):
        d2, i2 = tree.query(queries[again], k=need + 1, workers=-1)
        dist[again, : need + 1], idx[again, : need + 1] = d2.reshape(-1, need + 1), i2.reshape(-1, need + 1)
    return dist, idx


def local_deviation(points_mm: np.ndarray, deviations_mm: np.ndarray, smoothing_mm: float,
                    at: np.ndarray | None = None, tree: cKDTree | None = None, neighbours: int = NEIGHBOURS
                    ) -> LocalDeviation:
    """Average each point's deviation over its neighbours within ``smoothing_mm`` (at most ``neighbours``,
    itself included) and estimate its share of the surface (mm^2); only of the points ``at`` (indices)
    when given, their neighbours from the whole cloud (``tree``: its KD tree, if built)."""
    p = np.asarray(points_mm, dtype=np.float64)
    d = np.asarray(deviations_mm, dtype=np.float64)
    tree = tree or kd_tree(p)
    q = p if at is None else p[at]
    k = min(neighbours, len(p))
    kk = min(DENSITY_K, k - 2)  # the disk between the kk-th and the next neighbour holds kk + 1 points
    need = kk + 1 if kk >= 1 else k - 1
    smoothed = np.empty(len(q))
    share = np.empty(len(q))
    nearest = np.empty(len(q))
    for lo in range(0, len(q), _CHUNK):
        dist, idx = neighbours_within(tree, q[lo:lo + _CHUNK], k, smoothing_mm, max(need, min(1, k - 1)))
        inside = dist <= smoothing_mm
        smoothed[lo:lo + _CHUNK] = (np.take(d, idx, mode="clip") * inside).sum(axis=1) / inside.sum(axis=1)
        r_mid = 0.5 * (dist[:, kk] + dist[:, kk + 1]) if kk >= 1 else dist[:, -1]
        share[lo:lo + _CHUNK] = np.pi * r_mid**2 / (max(kk, 0) + 1)
        nearest[lo:lo + _CHUNK] = dist[:, min(1, k - 1)]
    return LocalDeviation(smoothed, share, nearest, at)


THIN_ABOVE_POINTS = 1_000_000  # larger clouds are screened on an even thinning first (:func:`_screened`)
SCREEN_CELL = 0.75  # the screening keeps one point per cube of this many smoothing radii
SCREEN_NEIGHBOURS = 16  # and averages over this many neighbours (within the smoothing radius)


_BALL_CHUNK = 4096  # centres a ball query of :func:`_within` takes at a time


def _within(tree: cKDTree, centres_mm: np.ndarray, radius_mm: float) -> np.ndarray:
    """Sorted indices of the tree's points within ``radius_mm`` of any of ``centres_mm`` (mm). The ball
    queries run :data:`_BALL_CHUNK` centres at a time into one mask: their lists of Python integers, about
    130 a centre at 1 mm spacing and each point found by about nine centres, would take several GB on a
    whole part whose surface lies near the band."""
    found = np.zeros(tree.n, bool)
    for lo in range(0, len(centres_mm), _BALL_CHUNK):
        hits = tree.query_ball_point(centres_mm[lo:lo + _BALL_CHUNK], radius_mm, workers=-1, return_sorted=False)
        found[np.concatenate([np.asarray(h, np.int64) for h in hits])] = True
    return np.flatnonzero(found)


def _screened(cloud: DeviationCloud, lower_mm: float, upper_mm: float, smoothing_mm: float,
              own: slice | None = None) -> LocalDeviation:
    """:func:`local_deviation` of the points that can be beyond the band: one point per cube of side
    :data:`SCREEN_CELL` ``* smoothing_mm`` is averaged first, over its :data:`SCREEN_NEIGHBOURS` nearest
    points within ``smoothing_mm`` (noise 1/4 of a point's, half the smoothing radius); every point within
    that cube's diagonal of one whose average is beyond the band narrowed by half its half-width is then
    averaged itself, as without the screening. The others (the surface within the band by that margin, five
    times the screening's noise at 0.05 mm per point) are left out; the spacing is the screening points'. ``own``:
    only the cloud's points in that range are averaged and spaced (a tile's, the others its halo)."""
    p, d, tree = cloud.points_mm, cloud.deviations_mm, cloud.tree
    cell = SCREEN_CELL * smoothing_mm
    centres, coarse = cloud.screening(smoothing_mm)
    margin = 0.25 * (upper_mm - lower_mm)
    near = centres[(coarse.smoothed_mm > upper_mm - margin) | (coarse.smoothed_mm < lower_mm + margin)]
    at = _within(tree, p[near], cell * np.sqrt(3.0))
    nearest = coarse.nearest_mm
    if own is not None:
        at = at[(at >= own.start) & (at < own.stop)]
        nearest = nearest[(centres >= own.start) & (centres < own.stop)]
    fine = local_deviation(p, d, smoothing_mm, at, tree)
    return LocalDeviation(fine.smoothed_mm, fine.area_mm2, nearest, at)


def _screening(p: np.ndarray, d: np.ndarray, smoothing_mm: float, tree: cKDTree
               ) -> tuple[np.ndarray, LocalDeviation]:
    """:func:`_screened`'s even thinning (one point per cube of :data:`SCREEN_CELL` ``* smoothing_mm``) and its
    points' deviations averaged over their :data:`SCREEN_NEIGHBOURS` nearest within ``smoothing_mm``: the same for
    every band (the areas at the band and at the verdict's guard band share it)."""
    centres = even_centres(p, SCREEN_CELL * smoothing_mm)
    return centres, local_deviation(p, d, smoothing_mm, centres, tree, SCREEN_NEIGHBOURS)


def local_deviations(cloud: DeviationCloud, lower_mm: float, upper_mm: float, smoothing_mm: float, screen: bool,
                     own: slice | None = None) -> LocalDeviation:
    """The averaged deviations and surface shares the areas beyond ``[lower_mm, upper_mm]`` are found from: of every
    point (of those in ``own``, the others only their neighbours: a tile's halo), or with ``screen`` of those near
    where an even thinning comes near the band (:func:`_screened`)."""
    if screen:
        return _screened(cloud, lower_mm, upper_mm, smoothing_mm, own)
    at = None if own is None else np.arange(own.start, own.stop)
    return local_deviation(cloud.points_mm, cloud.deviations_mm, smoothing_mm, at, cloud.tree)


def link_distance(spacing_mm: float, smoothing_mm: float) -> float:
    """How near two points beyond the band are linked into one area: three point spacings, at least
    ``smoothing_mm`` (mm)."""
    return max(3.0 * spacing_mm, smoothing_mm)


@dataclass(frozen=True)
class AreaPiece:
    """A linked set of points beyond the band on one ``side``: a whole area, or the part of one a tile holds (frame
    F). The sums its area's figures are made of (:meth:`area`): the surface (mm^2), the shares' first moment (the
    points weighted by their shares, mm^3), the extreme averaged deviation, the sum of the points' own deviations
    (mm) and their number. Pieces of one area add up to it (:meth:`joined`)."""

    side: str
    area_mm2: float
    moment_mm3: tuple[float, float, float]
    extreme_mm: float
    deviation_sum_mm: float
    points: int

    def joined(self, other: AreaPiece) -> AreaPiece:
        """This piece and ``other`` (the same side) as one."""
        pick = max if self.side == "upper" else min
        return AreaPiece(self.side, self.area_mm2 + other.area_mm2,
                         tuple(a + b for a, b in zip(self.moment_mm3, other.moment_mm3, strict=True)),
                         pick(self.extreme_mm, other.extreme_mm), self.deviation_sum_mm + other.deviation_sum_mm,
                         self.points + other.points)

    def area(self, id: int) -> DeviationArea:
        """The area these sums make, numbered ``id``: the shares' centroid, the extreme, the points' mean."""
        return DeviationArea(id, self.side, tuple(float(v) / self.area_mm2 for v in self.moment_mm3), self.area_mm2,
                             self.extreme_mm, self.deviation_sum_mm / self.points, self.points)


@dataclass(frozen=True)
class LinkedPoints:
    """The points beyond the band linked into pieces (:func:`linked_pieces`): the ``pieces`` and, per linked point,
    its index into the cloud (``at``) and its piece (``piece``)."""

    pieces: tuple[AreaPiece, ...]
    at: np.ndarray
    piece: np.ndarray


def linked_pieces(cloud: DeviationCloud, local: LocalDeviation, lower_mm: float, upper_mm: float, link_mm: float
                  ) -> LinkedPoints:
    """The points of ``local`` whose averaged deviation lies above ``upper_mm`` (or below ``lower_mm``) linked to
    those of the same side within ``link_mm``: each connected set one :class:`AreaPiece`, however small."""
    p, d = cloud.points_mm, cloud.deviations_mm
    at = np.arange(len(p)) if local.at is None else local.at
    pieces: list[AreaPiece] = []
    linked_at, linked_piece = [], []
    for side, beyond in (("upper", local.smoothed_mm > upper_mm), ("lower", local.smoothed_mm < lower_mm)):
        ids = np.nonzero(beyond)[0]
        if len(ids) == 0:
            continue
        pairs = cKDTree(p[at[ids]]).query_pairs(link_mm, output_type="ndarray")
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(ids), len(ids)))
        n, labels = connected_components(graph, directed=False)
        for c in range(n):
            members = ids[labels == c]
            w = local.area_mm2[members]
            s = local.smoothed_mm[members]
            pieces.append(AreaPiece(side, float(w.sum()), tuple(float(v) for v in (p[at[members]] * w[:, None]).sum(
                axis=0)), float(s.max() if side == "upper" else s.min()), float(d[at[members]].sum()), len(members)))
        linked_at.append(at[ids])
        linked_piece.append(labels + len(pieces) - n)
    if not pieces:
        return LinkedPoints((), np.zeros(0, np.int64), np.zeros(0, np.int64))
    return LinkedPoints(tuple(pieces), np.concatenate(linked_at), np.concatenate(linked_piece))


def areas_of(pieces: Sequence[AreaPiece], min_area_mm2: float) -> tuple[DeviationArea, ...]:
    """The areas of whole ``pieces`` at least ``min_area_mm2`` large, largest |extreme| first, ids 1, 2, ...."""
    kept = sorted((a for a in pieces if a.area_mm2 >= min_area_mm2), key=lambda a: -abs(a.extreme_mm))
    return tuple(a.area(i + 1) for i, a in enumerate(kept))


def find_deviation_areas(
    cloud: DeviationCloud,
    lower_mm: float,
    upper_mm: float,
    smoothing_mm: float = 5.0,
    min_area_mm2: float = 50.0,
    screen: bool | None = None,
) -> tuple[DeviationArea, ...]:
    """The areas beyond ``[lower_mm, upper_mm]`` of ``cloud`` (frame F), largest |extreme| first, with ids
    1, 2, ... in that order, each point's deviation averaged over ``smoothing_mm`` (``[inspection]
    area_smoothing_mm``), none smaller than ``min_area_mm2``. ``screen`` (default: above :data:`THIN_ABOVE_POINTS`
    points) averages only the points near where an even thinning of the cloud comes near the band
    (:func:`_screened`; docs/inspection-method.md, "Deviation areas")."""
    if screen is None:
        screen = len(cloud.points_mm) > THIN_ABOVE_POINTS
    local = local_deviations(cloud, lower_mm, upper_mm, smoothing_mm, screen)
    linked = linked_pieces(cloud, local, lower_mm, upper_mm, link_distance(local.spacing_mm, smoothing_mm))
    return areas_of(linked.pieces, min_area_mm2)
