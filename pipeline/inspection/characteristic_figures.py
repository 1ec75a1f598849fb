"""Figures of a quality engineer's report beside the colour maps: a section's deviation curve with its
tolerance band, a characteristic's trend over serials, and a close-up of each deviation area with its
surroundings (on a 4 m panel a 60 mm area is a few pixels of the whole-part map). Frame F, millimetres;
matplotlib's Agg canvas, no pyplot state.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from matplotlib.cm import ScalarMappable
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from tandemscan.pipeline.inspection.alignment import within
from tandemscan.pipeline.inspection.characteristics import CharacteristicResult
from tandemscan.pipeline.inspection.deviation_areas import DeviationArea
from tandemscan.pipeline.inspection.deviation_maps import DEVIATION_CMAP, png_bytes
from tandemscan.pipeline.inspection.region_points import closeup_radius_mm
from tandemscan.pipeline.inspection.spc import ControlChart

CLOSEUP_PX = 360  # a close-up's raster, pixels a side


def section_png(c: CharacteristicResult) -> bytes:
    """A section characteristic's averaged deviation along the CAD section curve, its tolerance band and
    the worst point (mm)."""
    assert c.curve is not None
    fig = Figure(figsize=(8.0, 3.0), dpi=100)
    ax = fig.add_axes((0.09, 0.17, 0.88, 0.7))
    ax.plot(c.curve.arc_mm, c.curve.deviation_mm, ".", ms=2.0, color="#1d3fbf", label="deviation (averaged)")
    ax.axhspan(c.lower_mm, c.upper_mm, color="#2fbf4a", alpha=0.15, label="tolerance band")
    for v in (c.lower_mm, c.upper_mm):
        ax.axhline(v, color="#2fbf4a", lw=1.0)
    ax.axhline(0.0, color="#444444", lw=0.6)
    ax.set_xlabel("along the CAD section curve, mm")
    ax.set_ylabel("deviation, mm")
    ax.set_title(f"{c.id} {c.name}: worst {c.actual_mm:+.3f} mm (U {c.uncertainty_mm:.3f}), {c.status}", fontsize=10)
    ax.legend(loc="upper right", fontsize=8)
    return png_bytes(fig)


@dataclass(frozen=True)
class CloseUp:
    """A deviation area's close-up: the PNG, the points it drew, how many of them lie beyond the band, and
    the square it shows (centre, frame F, and half side, mm, on the plane across the area's mean normal)."""

    area_id: int
    png: bytes
    points: int
    beyond_band: int
    centre_mm: tuple[float, float, float]
    half_side_mm: float

    def summary(self) -> dict:
        """JSON-ready, without the picture."""
        return {"area": self.area_id, "points": self.points, "beyond_band": self.beyond_band,
                "centre_mm": list(self.centre_mm), "half_side_mm": self.half_side_mm}


@dataclass(frozen=True)
class Surroundings:
    """The points a close-up is drawn from (frame F, mm; the whole inspected cloud, or those of the tiled cloud around
    the area, ``region_points.closeup_region``), their signed deviations (mm) and closest CAD unit normals."""

    points_mm: np.ndarray
    deviations_mm: np.ndarray
    normals: np.ndarray


def closeup(area: DeviationArea, around: Surroundings, lower_mm: float, upper_mm: float, norm: Normalize) -> CloseUp:
    """The area and its surroundings (``around``) seen along its mean CAD normal: the points within
    ``region_points.closeup_radius_mm`` of its centroid (three equivalent radii, at least 40 mm), each pixel the mean
    deviation of its points, the band's limits marked on the colour bar, the centroid labelled with the area's id."""
    points_mm, deviations_mm, normals = around.points_mm, around.deviations_mm, around.normals
    radius = closeup_radius_mm(area)
    centre = np.asarray(area.centroid_mm, float)
    near = within(points_mm, centre, radius * np.sqrt(2.0))
    n = normals[near].mean(axis=0) if len(near) else np.array([0.0, 0.0, 1.0])
    n /= max(np.linalg.norm(n), 1e-12)
    e1 = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    q = points_mm[near] - centre
    u, v = q @ e1, q @ e2
    inside = (np.abs(u) < radius) & (np.abs(v) < radius) & (normals[near] @ n > 0.0)
    u, v, d = u[inside], v[inside], deviations_mm[near][inside]
    col = np.clip(((u + radius) / (2 * radius) * CLOSEUP_PX).astype(np.int64), 0, CLOSEUP_PX - 1)
    row = np.clip(((radius - v) / (2 * radius) * CLOSEUP_PX).astype(np.int64), 0, CLOSEUP_PX - 1)
    flat = row * CLOSEUP_PX + col
    count = np.bincount(flat, minlength=CLOSEUP_PX**2)
    total = np.bincount(flat, weights=d, minlength=CLOSEUP_PX**2)
    mean = np.where(count > 0, total / np.maximum(count, 1), np.nan).reshape(CLOSEUP_PX, CLOSEUP_PX)
    fig = Figure(figsize=(4.6, 4.0), dpi=100)
    ax = fig.add_axes((0.14, 0.12, 0.66, 0.76))
    cax = fig.add_axes((0.84, 0.12, 0.04, 0.76))
    ax.set_facecolor("#d0d0d6")
    ax.imshow(mean, cmap=DEVIATION_CMAP, norm=norm, extent=(-radius, radius, -radius, radius),
              interpolation="nearest")
    colour = "#b3140d" if area.side == "upper" else "#1d3fbf"
    ax.annotate(f"#{area.id}", (0.0, 0.0), xytext=(16, 16), textcoords="offset points", fontsize=9,
                fontweight="bold", color=colour, bbox={"boxstyle": "round,pad=0.2", "fc": "white", "ec": colour},
                arrowprops={"arrowstyle": "-", "color": colour})
    ax.set_xlabel("across the area, mm")
    ax.set_ylabel("mm")
    ax.set_title(f"#{area.id} {area.side}: extreme {area.extreme_mm:+.3f} mm, {area.area_mm2:.0f} mm²\n"
                 f"at {centre[0]:.0f}, {centre[1]:.0f}, {centre[2]:.0f} mm (CAD)", fontsize=9)
    bar = fig.colorbar(ScalarMappable(norm, DEVIATION_CMAP), cax=cax, label="deviation, mm")
    for lim in (lower_mm, upper_mm):
        bar.ax.axhline(lim, color="black", lw=1.0)
    beyond = int(np.count_nonzero((d > upper_mm) | (d < lower_mm)))
    return CloseUp(area.id, png_bytes(fig), int(len(d)), beyond, tuple(map(float, centre)), float(radius))


def trend_png(c: CharacteristicResult, serials: Sequence[str], chart: ControlChart) -> bytes:
    """A characteristic's individuals chart over serials (the last one this inspection's): the values, the
    centre line, the control limits and the tolerance (mm)."""
    x = np.arange(len(chart.values))
    fig = Figure(figsize=(8.0, 3.0), dpi=100)
    ax = fig.add_axes((0.09, 0.25, 0.88, 0.62))
    ax.plot(x, chart.values, "o-", color="#1d3fbf", ms=4, lw=1.0, label="actual")
    ax.axhline(chart.mean_mm, color="#444444", lw=1.0, label=f"mean {chart.mean_mm:+.3f}")
    for v in (chart.ucl_mm, chart.lcl_mm):
        ax.axhline(v, color="#d7261e", lw=1.0, ls="--")
    for v in (c.lower_mm, c.upper_mm):
        ax.axhline(v, color="#2fbf4a", lw=1.2)
    ax.set_xticks(x, list(serials), rotation=45, fontsize=7, ha="right")
    ax.set_ylabel(f"{c.id} actual, mm")
    cpk = "" if chart.cpk is None else f", Cpk {chart.cpk:.2f}"
    ax.set_title(f"{c.id} {c.name} over {len(x)} serials{cpk}{': ' + chart.drift if chart.drift else ''}",
                 fontsize=9)
    ax.legend(loc="upper left", fontsize=7)
    return png_bytes(fig)
