"""Stitching quality: how well neighbouring scans lie on each other before and after correction.

For each pair of consecutive scans (world frame, mm) the overlap is the points of the later scan whose
nearest neighbour in the earlier one is closer than ``overlap_mm``; their distance to the earlier scan's
local plane (PCA of its k nearest points, normal in closed form) measures the layering that a stitching
error leaves; it is evaluated on an even subsample of the overlap (:data:`PAIR_SAMPLE` points). The picture
is the paper's cross-section view: a thin slice across the seam of the pair with the most overlap, each
scan's profile drawn relative to a quadratic fitted through the corrected points, before and after.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from matplotlib.figure import Figure
from scipy.spatial import cKDTree
from tandemscan.pipeline.geometry.frames import transform_points
from tandemscan.pipeline.inspection.alignment import fit_rigid
from tandemscan.pipeline.inspection.deviation_maps import png_bytes
from tandemscan.pipeline.registration.normals import scatter_matrices, smallest_eigenvectors

PAIR_SAMPLE = 2000  # overlap points of a pair the RMS is evaluated on, at most (an even subsample)
MAX_PAIR_LABELS = 60  # the stitching figure names at most this many pairs (evenly chosen) under its bars


@dataclass(frozen=True)
class PairOverlap:
    """Overlap of scan ``j`` onto scan ``i``: point count and RMS point-to-plane distance (mm)."""

    i: int
    j: int
    points: int
    rms_before_mm: float
    rms_after_mm: float | None


def _tree(points: np.ndarray) -> cKDTree:
    """A KD tree of one scan's points: built median-free and uncompacted, which builds twice and answers
    nearest-neighbour queries three times as fast on scans of 20 000 to 35 000 points as the defaults."""
    return cKDTree(points, balanced_tree=False, compact_nodes=False)


def _plane_distances(points: np.ndarray, reference: np.ndarray, tree: cKDTree, k: int) -> np.ndarray:
    """Point-to-local-plane distance of ``points`` to ``reference`` (``tree`` is its KD tree): the plane
    through the mean of the k nearest reference points, normal to their least spread. One thread: a pair's
    2000 queries cost less than starting threads for them."""
    _, idx = tree.query(points, k=max(3, min(k, len(reference))))
    nb = reference[idx]  # (N, k, 3)
    centre = nb.mean(axis=1)
    normals = smallest_eigenvectors(scatter_matrices(nb - centre[:, None]))
    return np.abs(np.einsum("ni,ni->n", points - centre, normals))


RIGID_TOLERANCE_MM = 1e-6  # a scan before and after correction is one rigid motion apart to this


def rigid_motion(moved: np.ndarray, here: np.ndarray) -> np.ndarray | None:
    """4x4 ``T`` with ``moved = T here`` (the same points, mm, after one rigid motion), or None where no
    rigid motion maps every point to within :data:`RIGID_TOLERANCE_MM`."""
    if len(here) != len(moved) or len(here) < 3:
        return None
    pick = np.unique(np.linspace(0, len(here) - 1, 64).astype(np.int64))
    T = fit_rigid(here[pick], moved[pick])
    off = transform_points(T, here) - moved
    return T if float(np.einsum("ij,ij->i", off, off).max()) <= RIGID_TOLERANCE_MM**2 else None


def overlap_quality(
    scans_before: Sequence[np.ndarray],
    scans_after: Sequence[np.ndarray] | None = None,
    overlap_mm: float = 2.0,
    k: int = 10,
    max_points: int = 20_000,
    sample: int = PAIR_SAMPLE,
) -> list[PairOverlap]:
    """Per consecutive pair (i, i+1): overlap size and RMS point-to-plane distance, before and after.

    ``scans_after`` holds the same scans (same order and point order) after correction. The overlap is
    chosen on the corrected scans when given, so both columns compare the same points: the points of an even
    subsample of scan i+1 (at most ``max_points``) within ``overlap_mm`` of scan i, looked for among
    ``2 * sample`` of them first and among all where fewer than ``sample / 4`` overlap (then ``points`` is
    their count, else the count scaled up from the sample's). The RMS is a statistic of an even subsample of
    the overlap found, at most ``sample`` points (2000 put it within about 2 %).
    """
    if scans_after is not None and len(scans_after) != len(scans_before):
        raise ValueError(f"{len(scans_before)} scans before correction but {len(scans_after)} after")
    pairs = []
    select = scans_after if scans_after is not None else scans_before
    b = b0 = None  # a pair's later scan is the next one's earlier: each scan of a list placed once
    for i in range(len(scans_before) - 1):
        a, b = (b if b is not None else np.asarray(select[i], float)), np.asarray(select[i + 1], float)
        a0, b0 = b0, None  # scan i before the correction, where the previous pair placed it
        if len(a) < 3 or len(b) == 0:
            continue
        b_idx = np.arange(len(b))[:: max(1, len(b) // max_points)]
        tree_a = _tree(a)
        look = b_idx[:: max(1, len(b_idx) // (2 * sample))]
        over = look[tree_a.query(b[look], distance_upper_bound=overlap_mm)[0] < overlap_mm]
        if len(over) < sample // 4 and len(look) < len(b_idx):  # a small overlap: look at every point
            look = b_idx
            over = look[tree_a.query(b[look], distance_upper_bound=overlap_mm)[0] < overlap_mm]
        if not len(over):
            continue
        count = round(len(over) * len(b_idx) / len(look))
        over = over[:: max(1, len(over) // sample)]  # the planes of a sample of the overlap only
        rms_after = None
        if scans_after is not None:
            a0 = a0 if a0 is not None else np.asarray(scans_before[i], float)
            b0 = np.asarray(scans_before[i + 1], float)
            T = rigid_motion(a, a0)  # scan i moved by the correction: its tree serves before and after
            if T is None:
                dist = _plane_distances(b[over], a, tree_a, k)
                dist0 = _plane_distances(b0[over], a0, _tree(a0), k)
            else:  # after and before asked of the one tree at once (each point's answer is its own)
                both = _plane_distances(np.concatenate([b[over], transform_points(T, b0[over])]), a, tree_a, k)
                dist, dist0 = both[: len(over)], both[len(over):]
            rms_after = float(np.sqrt(np.mean(dist**2)))
            rms_before = float(np.sqrt(np.mean(dist0**2)))
        else:
            rms_before = float(np.sqrt(np.mean(_plane_distances(b[over], a, tree_a, k) ** 2)))
        pairs.append(PairOverlap(i, i + 1, count, rms_before, rms_after))
    return pairs


def _section(a: np.ndarray, b: np.ndarray, overlap_mm: float):
    """Frame of a slice across the seam of scans a and b: (centre, along-seam-normal u, surface normal n,
    slice normal w), or None when they do not overlap."""
    nn, _ = _tree(a).query(b)
    ov = b[nn < overlap_mm]
    if len(ov) < 10:
        return None
    c = ov.mean(axis=0)
    _, vecs = np.linalg.eigh(np.cov((ov - c).T))
    n = vecs[:, 0]
    u = b.mean(axis=0) - a.mean(axis=0)
    u -= (u @ n) * n
    if np.linalg.norm(u) < 1e-9:
        u = vecs[:, 2]
    u /= np.linalg.norm(u)
    return c, u, n, np.cross(u, n)


def stitching_png(
    scans_before: Sequence[np.ndarray],
    scans_after: Sequence[np.ndarray] | None,
    pairs: Sequence[PairOverlap],
    overlap_mm: float = 2.0,
    slab_mm: float = 1.5,
) -> bytes | None:
    """Bar chart of per-pair overlap RMS (before/after) and a cross-section of the pair with the most overlap.

    None when no pair overlaps.
    """
    if not pairs:
        return None
    best = max(pairs, key=lambda p: p.points)
    final = scans_after if scans_after is not None else scans_before
    frame = _section(np.asarray(final[best.i], float), np.asarray(final[best.j], float), overlap_mm)
    fig = Figure(figsize=(9.0, 6.5), dpi=110)  # fixed axes, as the maps: no layout engine
    bar = fig.add_axes((0.08, 0.64, 0.9, 0.3))
    axes = [fig.add_axes((0.1, 0.08, 0.38, 0.38)), fig.add_axes((0.6, 0.08, 0.38, 0.38))]
    x = np.arange(len(pairs))
    bar.bar(x - 0.2, [p.rms_before_mm * 1000 for p in pairs], 0.4, label="before correction", color="#d7261e")
    if scans_after is not None:
        bar.bar(x + 0.2, [p.rms_after_mm * 1000 for p in pairs], 0.4, label="after correction", color="#2fbf4a")
    every = max(1, int(np.ceil(len(pairs) / MAX_PAIR_LABELS)))  # more would overlap
    bar.set_xticks(x[::every], [f"{p.i}-{p.j}" for p in pairs[::every]], fontsize=7,
                   rotation=90 if len(pairs) > 20 else 0)
    bar.set_ylabel("overlap RMS, um")
    bar.set_xlabel("neighbouring scans")
    bar.set_title("Distance between neighbouring scans in their overlap")
    bar.legend(fontsize=8, loc="upper right")
    if frame is None:
        for ax in axes:
            ax.set_axis_off()
        return png_bytes(fig)
    c, u, n, w = frame

    def section(scans, idx):
        p = np.asarray(scans[idx], float) - c
        sl = p[np.abs(p @ w) < slab_mm]
        return sl @ u, sl @ n

    ref = [section(final, best.i), section(final, best.j)]
    s_all, h_all = np.concatenate([s for s, _ in ref]), np.concatenate([h for _, h in ref])
    fit = np.polyfit(s_all, h_all, 2) if len(s_all) > 3 else np.zeros(3)  # through the corrected points
    panels = [("before correction", scans_before)]
    if scans_after is not None:
        panels.append(("after correction", scans_after))
    for ax, (label, scans) in zip(axes, panels, strict=False):
        curves = [(idx, colour, *section(scans, idx)) for idx, colour in ((best.i, "#1d3fbf"), (best.j, "#d7261e"))]
        for idx, colour, s, h in curves:
            ax.scatter(s, (h - np.polyval(fit, s)) * 1000, s=2, color=colour, label=f"scan {idx}")
        ax.set_title(f"section across seam {best.i}-{best.j}, {label}", fontsize=9)
        ax.set_xlabel("along the section, mm")
        ax.set_ylabel("height about the fit, um")
        ax.legend(fontsize=7, markerscale=4)
    if scans_after is None:
        axes[1].set_axis_off()
    return png_bytes(fig)
