"""Alignment by a datum reference frame (3-2-1): after a best fit has placed the cloud near the CAD, three
datum features are fitted to the measured points of their patches and to the CAD sampled there, and the
cloud is moved so that its frame of the three lands on the CAD's (docs/inspection.md, "Inspection
templates"). A best fit spreads a deformed region over the whole part; the datum frame leaves every
deviation where it is, relative to the datums.

Features, each fitted by least squares to a plane through its patch's points: the primary ``plane`` fixes
the frame's z axis and its height; the secondary ``line`` is the intersection of its plane with the primary
(the x axis and, across it, y); the tertiary ``point`` is where its plane meets that line (the origin along
x). Frame F (CAD), millimetres, 4x4 ``T_F_W``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.inspection.alignment import Alignment
from tandemscan.pipeline.inspection.characteristics import sample_surface
from tandemscan.pipeline.inspection.inspect import CadSurface, InspectionError

CAD_SAMPLES_PER_MM2 = 0.5  # the CAD side of a datum patch is sampled this densely
MIN_POINTS = 30  # a datum feature is fitted to at least this many measured points


@dataclass(frozen=True)
class DatumPatch:
    """One datum feature: ``plane``, ``line`` or ``point``, fitted in the box ``min_mm``-``max_mm`` (F)."""

    feature: str
    name: str
    min_mm: tuple[float, float, float]
    max_mm: tuple[float, float, float]


def fit_plane(points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(centroid, unit normal, RMS distance) of the least-squares plane through the points (mm)."""
    c = points_mm.mean(axis=0)
    _, s, vt = np.linalg.svd(points_mm - c, full_matrices=False)
    return c, vt[2], float(s[2] / np.sqrt(len(points_mm)))


def frame_of_planes(planes: Sequence[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """The 3-2-1 frame (4x4, frame of the points) of three planes (point, normal): z the primary's normal,
    x along the primary's intersection with the secondary, origin where the tertiary meets that line."""
    (p1, n1), (p2, n2), (p3, n3) = planes
    x = np.cross(n1, n2)
    if np.linalg.norm(x) < 0.1:
        raise InspectionError("the primary and secondary datums are nearly parallel: they fix no direction")
    x /= np.linalg.norm(x)
    z = n1 / np.linalg.norm(n1)
    y = np.cross(z, x)
    A = np.array([n1, n2, n3])
    if abs(np.linalg.det(A)) < 0.05:
        raise InspectionError("the three datums do not meet in a point")
    origin = np.linalg.solve(A, [n1 @ p1, n2 @ p2, n3 @ p3])
    return F.make_transform(np.column_stack([x, y, z]), origin)


def _cad_points(surface: CadSurface, patch: DatumPatch) -> np.ndarray:
    """The CAD surface sampled evenly inside the patch's box (F, mm)."""
    v = np.asarray(surface.mesh.vertices, float)
    t = np.asarray(surface.mesh.triangles)
    lo, hi = np.asarray(patch.min_mm), np.asarray(patch.max_mm)
    near = np.all((v[t].max(axis=1) >= lo) & (v[t].min(axis=1) <= hi), axis=1)
    p = sample_surface(v, t[near], CAD_SAMPLES_PER_MM2) if near.any() else np.zeros((0, 3))
    return p[np.all((p >= lo) & (p <= hi), axis=1)]


def align_datums(surface: CadSurface, points_W_mm: np.ndarray, best_fit: Alignment, patches: Sequence[DatumPatch]
                 ) -> Alignment:
    """``T_F_W`` of the datum reference frame of ``patches`` (plane, line, point; module docstring), from
    the cloud (W) placed in F by ``best_fit``; residual: the RMS of the three measured planes' fits (mm)."""
    if [p.feature for p in patches] != ["plane", "line", "point"]:
        raise InspectionError("a datum reference frame is a plane, a line and a point, in that order")
    placed = F.transform_points(best_fit.T_F_W, points_W_mm)
    measured, nominal, rms = [], [], []
    for patch in patches:
        lo, hi = np.asarray(patch.min_mm), np.asarray(patch.max_mm)
        inside = placed[np.all((placed >= lo) & (placed <= hi), axis=1)]
        cad = _cad_points(surface, patch)
        if len(inside) < MIN_POINTS or len(cad) < MIN_POINTS:
            raise InspectionError(f"datum {patch.feature} {patch.name!r}: {len(inside)} measured and {len(cad)} CAD "
                                  f"points in its patch (at least {MIN_POINTS} each)")
        c, n, r = fit_plane(inside)
        c0, n0, _ = fit_plane(cad)
        measured.append((c, n if n @ n0 > 0 else -n))
        nominal.append((c0, n0))
        rms.append(r)
    T_F_placed = frame_of_planes(nominal) @ F.invert(frame_of_planes(measured))
    names = ", ".join(f"{p.feature} {p.name}" for p in patches)
    return replace(best_fit, method="datums", T_F_W=T_F_placed @ best_fit.T_F_W,
                   residual_mm=float(np.sqrt(np.mean(np.square(rms)))),
                   start=f"{best_fit.start}, then a best fit, then the datums {names}")
