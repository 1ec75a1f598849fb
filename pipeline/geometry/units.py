"""The length units a customer's files come in, and the check that catches a file read in the wrong one.

Inside, everything is in millimetres (docs/architecture.md); a mesh or cloud file in another unit is scaled once,
where it is read (``[part] mesh_units``, ``[inspection] cad_units`` and ``cloud_units``; the CLI's
``--part-units``, ``--cad-units``, ``--cloud-units``). A file read in the wrong unit is off by a factor of 10,
25.4 or 1000: a part a thousandth of its size, or a cloud a thousand times larger than its CAD.
"""

from __future__ import annotations

import numpy as np

#: millimetres per unit of a file's coordinates
MM_PER_UNIT = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}

#: a part whose largest side is below this (mm) is far smaller than the cell measures: perhaps its file is in metres
SMALL_PART_MM = 100.0
#: a cloud this many times larger than its CAD, or smaller by :data:`MAX_SMALLER`, is in another unit than the CAD
MAX_LARGER = 50.0
MAX_SMALLER = 200.0


#: rows a pass over a cloud's (N, 3) columns takes at a time (:func:`box_mm`, :func:`in_box_mm`): a column's strided
#: reads of a block stay in the cache (an 8 M-point cloud's box or box test in 0.4 of the time of whole columns)
BOX_ROWS = 65_536


def box_mm(points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi), (3,) each: the corners of the points' (N, 3) axis-aligned bounding box (mm), reduced a column of a
    block of :data:`BOX_ROWS` rows at a time (the same values as ``min(axis=0)`` / ``max(axis=0)``, which run a
    third as fast on (N, 3) rows; no points: ``ValueError``, as they raise)."""
    p = np.asarray(points_mm, float)
    lo, hi = (np.array([p[:BOX_ROWS, i].min() for i in range(3)], np.float64),
              np.array([p[:BOX_ROWS, i].max() for i in range(3)], np.float64))
    for at in range(BOX_ROWS, len(p), BOX_ROWS):
        rows = p[at:at + BOX_ROWS]
        np.minimum(lo, [rows[:, i].min() for i in range(3)], out=lo)
        np.maximum(hi, [rows[:, i].max() for i in range(3)], out=hi)
    return lo, hi


def in_box_mm(points_mm: np.ndarray, lo_mm, hi_mm) -> np.ndarray:
    """(N,) bool: the points (N, 3) inside the axis-aligned box from ``lo_mm`` to ``hi_mm`` (3,) each, bounds
    inclusive (mm), compared a column of a block of :data:`BOX_ROWS` rows at a time (the answer of
    ``np.all((p >= lo) & (p <= hi), axis=1)``, in a fifth of its time on (N, 3) rows)."""
    p, lo, hi = np.asarray(points_mm), np.asarray(lo_mm), np.asarray(hi_mm)
    inside = np.empty(len(p), bool)
    for at in range(0, len(p), BOX_ROWS):
        rows, out = p[at:at + BOX_ROWS], inside[at:at + BOX_ROWS]
        np.greater_equal(rows[:, 0], lo[0], out=out)
        out &= rows[:, 0] <= hi[0]
        for i in (1, 2):
            out &= rows[:, i] >= lo[i]
            out &= rows[:, i] <= hi[i]
    return inside


def extent_mm(points_mm: np.ndarray) -> np.ndarray:
    """(3,) the sides of the points' axis-aligned bounding box (mm)."""
    lo, hi = box_mm(points_mm)
    return hi - lo


def size_words(extent: np.ndarray) -> str:
    """``"0.90 x 0.60 x 0.35 mm"``: a bounding box's sides in words (mm)."""
    return " x ".join(f"{x:.3g}" for x in extent) + " mm"


def small_part_hint(extent: np.ndarray, option: str) -> str:
    """For a part whose largest side is under :data:`SMALL_PART_MM`: the sentence that names its size and the
    units its file may really be in (those that make it :data:`SMALL_PART_MM` to 40 m long), with ``option``
    (the CLI's, e.g. ``--part-units``); else ""."""
    largest = float(np.max(extent))
    if largest >= SMALL_PART_MM:
        return ""
    units = [u for u, mm in MM_PER_UNIT.items() if SMALL_PART_MM <= largest * mm <= 40_000.0] or ["m"]
    return (f"the part is {size_words(extent)}, far smaller than the cell measures: if its file is not in "
            f"millimetres, give {option} {' or '.join(units)}")


def scale_mismatch(cloud_extent: np.ndarray, cad_extent: np.ndarray, max_larger: float = MAX_LARGER,
                   max_smaller: float = MAX_SMALLER) -> str:
    """Where a cloud's size and its CAD's differ by more than a part and its surroundings can (the cloud more
    than ``max_larger`` times larger, or ``max_smaller`` times smaller): the sentence that says so and names
    the options; else ""."""
    cloud, cad = float(np.max(cloud_extent)), float(np.max(cad_extent))
    if cad <= 0.0 or cloud <= 0.0:
        return ""
    ratio = cloud / cad
    if 1.0 / max_smaller <= ratio <= max_larger:
        return ""
    unit = min((u for u in MM_PER_UNIT if u != "mm"),
               key=lambda u: abs(np.log(max(ratio, 1.0 / ratio) / MM_PER_UNIT[u])))
    which = ("the CAD", "--cad-units") if ratio > 1.0 else ("the cloud", "--cloud-units")
    name = {"in": "inches", "m": "metres", "cm": "centimetres"}[unit]
    return (f"the cloud spans {size_words(cloud_extent)}, the CAD {size_words(cad_extent)}: "
            f"{max(ratio, 1.0 / ratio):.4g} times {'larger' if ratio > 1.0 else 'smaller'}; both files are read in "
            f"millimetres: if {which[0]} is in {name}, give {which[1]} {unit} ([part] mesh_units in a job)")
