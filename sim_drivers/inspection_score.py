"""Scoring an inspection against the simulated truth: how far the alignment's ``T_F_W`` is from the world's,
and how well the report's deviation areas found the as-built part's deviations (``[sim.as_built]``).

The job's truth scorer (``ground_truth.inspection``, :mod:`tandemscan.sim_drivers.truth_observer`), the benchmarks and
the tests call this; the product never sees what it reads. Frame F, mm, degrees in the
figures it returns.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from tandemscan.config.models import CellConfig
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.inspection.deviation_areas import DeviationArea
from tandemscan.pipeline.inspection.inspect import CadSurface
from tandemscan.sim_drivers.as_built import normal_deviation

CENTROID_MATCH_MM = 10.0  # a report area finds a deviation when its centroid is this close (same side)


def alignment_error(T_F_W: np.ndarray, T_F_W_true: np.ndarray, at_F_mm: np.ndarray) -> tuple[float, float]:
    """(mm, deg): how far the estimate moves the point ``at_F_mm`` (frame F, e.g. the part's centre) from
    where the truth puts it, and the angle between the two rotations."""
    p_W = F.transform_points(F.invert(T_F_W_true), np.asarray(at_F_mm, float)[None])
    moved = F.transform_points(T_F_W, p_W)[0] - np.asarray(at_F_mm, float)
    return float(np.linalg.norm(moved)), float(np.degrees(F.rotation_angle(T_F_W @ F.invert(T_F_W_true))))


@dataclass(frozen=True)
class DeviationTruth:
    """One configured deviation as the measured cloud shows it: its side, the centroid of the CAD points
    where it exceeds the band and its extreme there (mm); ``visible`` false when it nowhere does."""

    index: int
    kind: str
    side: str
    centroid_mm: tuple[float, float, float]
    extreme_mm: float
    visible: bool


def deviation_truths(config: CellConfig, surface: CadSurface, points_F_mm: np.ndarray) -> list[DeviationTruth]:
    """The truth of every ``[sim.as_built]`` deviation at the measured points (placed in F by the true
    ``T_F_W``): where along the CAD normal it moves the surface beyond the ``[inspection]`` band."""
    lo, hi = config.inspection.tolerance_lower_mm, config.inspection.tolerance_upper_mm
    out = []
    for i, dev in enumerate(config.sim.as_built.deviations):
        cad_points, d = normal_deviation(dev, surface, points_F_mm)
        side = "upper" if abs(d.max()) >= abs(d.min()) else "lower"
        beyond = d > hi if side == "upper" else d < lo
        if not beyond.any():
            out.append(DeviationTruth(i, dev.kind, side, (np.nan,) * 3, 0.0, False))
            continue
        extreme = float(d[beyond].max() if side == "upper" else d[beyond].min())
        out.append(DeviationTruth(i, dev.kind, side, tuple(map(float, cad_points[beyond].mean(axis=0))), extreme,
                                  True))
    return out


def score_areas(truths: list[DeviationTruth], areas: tuple[DeviationArea, ...]) -> dict:
    """Found, missed and false areas: each visible truth takes the nearest area of its side within
    :data:`CENTROID_MATCH_MM`; areas no truth took are false. Errors per found deviation (mm)."""
    taken: set[int] = set()
    rows = []
    for t in truths:
        if not t.visible:
            continue
        same = [a for a in areas if a.side == t.side and a.id not in taken]
        dist = [float(np.linalg.norm(np.subtract(a.centroid_mm, t.centroid_mm))) for a in same]
        best = int(np.argmin(dist)) if dist else -1
        row = {"deviation": t.index, "kind": t.kind, "side": t.side, "true_extreme_mm": round(t.extreme_mm, 4)}
        if best >= 0 and dist[best] <= CENTROID_MATCH_MM:
            a = same[best]
            taken.add(a.id)
            row |= {"found": True, "area": a.id, "centroid_err_mm": round(dist[best], 2),
                    "extreme_err_mm": round(abs(a.extreme_mm - t.extreme_mm), 4), "area_mm2": round(a.area_mm2, 0)}
        else:
            row |= {"found": False, "nearest_mm": round(min(dist), 1) if dist else None}
        rows.append(row)
    false = [a for a in areas if a.id not in taken]
    found = [r for r in rows if r["found"]]
    return {
        "deviations": len(rows),
        "found": len(found),
        "missed": len(rows) - len(found),
        "false_regions": len(false),
        "false_area_mm2_max": round(max((a.area_mm2 for a in false), default=0.0), 1),
        "centroid_err_mm_max": max((r["centroid_err_mm"] for r in found), default=None),
        "extreme_err_mm_max": max((r["extreme_err_mm"] for r in found), default=None),
        "per_deviation": rows,
    }
