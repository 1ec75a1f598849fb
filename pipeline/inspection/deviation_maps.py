"""Headless pictures of an inspection: deviation colour maps from standard views and the histogram.

Rendering is done without a display: the CAD mesh is ray cast orthographically with Open3D (grey, lit from
the viewer), measured points are z-buffered on the same pixel grid and coloured by their deviation, and
matplotlib (Agg canvas, no pyplot state) adds axes, scale and colour bar. Frame F, millimetres; the view
directions assume the part convention (length along x, nose towards +x, z up).
"""

from __future__ import annotations

import functools
import io
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.cm import ScalarMappable
from matplotlib.colors import Colormap, LinearSegmentedColormap, Normalize
from matplotlib.figure import Figure
from scipy.spatial import cKDTree
from tandemscan.pipeline.inspection.inspect import CadSurface, DeviationStats, ToleranceResult

# Blue (below) - cyan - green (on CAD) - yellow - red (above): what GOM and PolyWorks users read at a glance.
DEVIATION_CMAP = LinearSegmentedColormap.from_list(
    "deviation", ["#1d3fbf", "#20b7e0", "#2fbf4a", "#f2e02a", "#d7261e"]
)
NO_MESH_RGB = np.array([1.0, 1.0, 1.0])


@dataclass(frozen=True)
class View:
    """An orthographic view: ``forward`` is the viewing direction (from the eye into the scene), frame F."""

    name: str
    forward: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)


STANDARD_VIEWS = {  # keys as in InspectionConfig.views
    "isometric": View("isometric", (-1.0, 1.0, -0.8)),
    "front": View("front (from +x)", (-1.0, 0.0, 0.0)),
    "left": View("left (from -y)", (0.0, 1.0, 0.0)),
    "right": View("right (from +y)", (0.0, -1.0, 0.0)),
    "top": View("top (from +z)", (0.0, 0.0, -1.0), up=(0.0, 1.0, 0.0)),
    "back": View("back (from -x)", (1.0, 0.0, 0.0)),
}


def facing_isometric(normals: np.ndarray, name: str = "isometric") -> View:
    """An isometric view from above, on the side the measured surface mostly faces (mean of ``normals``,
    horizontal part); the standard isometric when the normals cancel out."""
    h = np.asarray(normals, float).mean(axis=0) if len(normals) else np.zeros(3)
    h[2] = 0.0
    if np.linalg.norm(h) < 0.1:
        return STANDARD_VIEWS["isometric"]
    h /= np.linalg.norm(h)
    return View(name, tuple(-(h + [0.0, 0.0, 0.8 / np.sqrt(2)])))


PNG_COMPRESS_LEVEL = 1  # zlib's fastest: a third of the encoding time of its default for 10 % more bytes


def png_bytes(fig: Figure) -> bytes:
    """The figure as PNG bytes (Agg canvas)."""
    buf = io.BytesIO()
    FigureCanvasAgg(fig).print_png(buf, pil_kwargs={"compress_level": PNG_COMPRESS_LEVEL})
    return buf.getvalue()


def _camera(view: View) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    f = np.asarray(view.forward, float)
    f /= np.linalg.norm(f)
    r = np.cross(f, np.asarray(view.up, float))
    r /= np.linalg.norm(r)
    return f, r, np.cross(r, f)


@dataclass(frozen=True)
class MapPoints:
    """What a colour map draws: points (frame F, mm), a value each (a deviation or an uncertainty, mm), the unit
    normals of their closest CAD triangles (None: any pixel in front shows them) and their typical spacing (mm;
    None: measured, :func:`typical_spacing`)."""

    points_mm: np.ndarray
    values: np.ndarray
    normals: np.ndarray | None = None
    spacing_mm: float | None = None

    def subset(self, keep: np.ndarray) -> MapPoints:
        """The points ``keep`` (a mask or indices) selects, at the same spacing."""
        return MapPoints(self.points_mm[keep], self.values[keep],
                         None if self.normals is None else self.normals[keep], self.spacing_mm)


@dataclass(frozen=True)
class ColourScale:
    """How a map's values become colours: ``norm`` over ``cmap``, a colour bar labelled ``label`` with a line at
    each of ``marks`` (the tolerance limits, mm)."""

    norm: Normalize
    marks: tuple[float, ...] = ()
    cmap: Colormap = field(default_factory=lambda: DEVIATION_CMAP)
    label: str = "deviation, mm"


@dataclass(frozen=True)
class Rendering:
    """An RGB image (rows top-down, float 0-1) and its extent on the view plane, mm (left, right, bottom, top)."""

    rgb: np.ndarray
    extent_mm: tuple[float, float, float, float]
    coloured_px: int


@dataclass(frozen=True)
class _Background:
    """The ray-cast CAD picture of one view: grey shading, depth of the first hit (mm along ``f`` from the
    plane ``depth0``, inf where the ray misses) and the pixel grid (top-left origin ``x0, y1``, pixel ``px``)."""

    f: np.ndarray
    r: np.ndarray
    u: np.ndarray
    rgb: np.ndarray
    t_hit: np.ndarray
    extent_mm: tuple[float, float, float, float]
    px: float
    depth0: float
    triangle_ids: np.ndarray  # (H, W) the CAD triangle each pixel shows, INVALID_ID where the ray misses
    normals: np.ndarray  # (H, W, 3) that triangle's unit normal (F), zero where the ray misses


@functools.lru_cache(maxsize=1)  # the first view's other maps (coverage, upper/lower, U) reuse its background
def _background(surface: CadSurface, view: View, width_px: int) -> _Background:
    f, r, u = _camera(view)
    corners = np.asarray(surface.mesh.get_axis_aligned_bounding_box().get_box_points())
    sx, sy = corners @ r, corners @ u
    pad = 0.04 * max(np.ptp(sx), np.ptp(sy))
    x0, x1, y0, y1 = sx.min() - pad, sx.max() + pad, sy.min() - pad, sy.max() + pad
    px = (x1 - x0) / width_px
    height_px = max(1, int(np.ceil((y1 - y0) / px)))
    depth0 = float((corners @ f).min()) - 10.0
    rays = np.empty((height_px, width_px, 6), np.float32)
    top_left = (x0 + 0.5 * px) * r + (y1 - 0.5 * px) * u + depth0 * f - surface.origin_mm
    rays[..., :3] = (top_left + np.arange(width_px)[:, None] * (px * r))[None].astype(np.float32)
    rays[..., :3] -= (np.arange(height_px)[:, None] * (px * u))[:, None].astype(np.float32)
    rays[..., 3:] = f.astype(np.float32)
    hit = surface.scene.cast_rays(o3d.core.Tensor(rays))
    t_hit = hit["t_hit"].numpy()
    shade = 0.35 + 0.55 * np.abs(hit["primitive_normals"].numpy() @ f.astype(np.float32))
    rgb = np.where(np.isfinite(t_hit)[..., None], shade[..., None] * np.float32([0.82, 0.82, 0.85]), NO_MESH_RGB)
    normals = np.where(np.isfinite(t_hit)[..., None], hit["primitive_normals"].numpy(), np.float32(0.0))
    return _Background(f, r, u, rgb.astype(np.float32), t_hit, (x0, x1, y0, y1), px, depth0,
                       hit["primitive_ids"].numpy(), normals)


def render_view(
    surface: CadSurface,
    drawn: MapPoints,
    view: View,
    norm: Normalize,
    width_px: int = 900,
    cmap: Colormap = DEVIATION_CMAP,
    depth_margin_mm: float | None = None,
) -> Rendering:
    """Ray-cast the CAD mesh along ``view`` and paint the visible points of ``drawn`` coloured by their values.

    A point is visible when it lies no more than ``depth_margin_mm`` (default: three pixels plus the colour
    range) behind the first CAD surface on its pixel; among visible points the nearest wins each pixel, and
    points are splatted over as many pixels as their spacing needs, so gaps in the data stay grey. With
    normals (of each point's closest CAD triangle) a point is drawn only
    on pixels whose CAD triangle faces the same way as its own, from whichever side the camera sees it: an
    open panel shows its measured points from outside and from inside, a thin closed part's far wall stays
    hidden behind its near one (docs/inspection-method.md, "Method")."""
    bg = _background(surface, view, width_px)
    f, r, u, px = bg.f, bg.r, bg.u, bg.px
    x0, x1, y0, y1 = bg.extent_mm
    height_px = bg.t_hit.shape[0]
    p = np.asarray(drawn.points_mm, float)
    values = np.asarray(drawn.values, float)
    spacing = typical_spacing(p) if drawn.spacing_mm is None else drawn.spacing_mm
    own = None if drawn.normals is None else np.asarray(drawn.normals, np.float32)
    c = np.floor((p @ r - x0) / px).astype(np.int64)
    rr = np.floor((y1 - p @ u) / px).astype(np.int64)
    depth = p @ f - bg.depth0
    splat = int(min(6, max(1, np.ceil(1.5 * spacing / px))))
    margin = depth_margin_mm if depth_margin_mm is not None else 3 * px + 2.0 * max(abs(norm.vmin), abs(norm.vmax))
    order = np.argsort(depth, kind="stable")  # z-buffer of ranks: each pixel keeps its nearest point
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order))
    nearest = np.full(height_px * width_px, len(order), np.int64)
    for dr in range(splat):
        for dc in range(splat):
            cc, r2 = c + dc - splat // 2, rr + dr - splat // 2
            ok = (cc >= 0) & (cc < width_px) & (r2 >= 0) & (r2 < height_px)
            ok[ok] &= depth[ok] <= bg.t_hit[r2[ok], cc[ok]] + margin
            if own is not None:  # the same sheet as the pixel shows, seen from either side
                ok[ok] &= np.einsum("ij,ij->i", own[ok], bg.normals[r2[ok], cc[ok]]) > 0.0
            np.minimum.at(nearest, r2[ok] * width_px + cc[ok], rank[ok])
    win_pix = np.flatnonzero(nearest < len(order))
    win_idx = order[nearest[win_pix]]
    flat = bg.rgb.reshape(-1, 3).copy()
    flat[win_pix] = cmap(norm(values[win_idx]))[:, :3]
    return Rendering(flat.reshape(height_px, width_px, 3), bg.extent_mm, len(win_pix))


def typical_spacing(points_mm: np.ndarray, sample: int = 2000) -> float:
    """Median nearest-neighbour distance of the cloud, mm (on a subsample of the queries)."""
    if len(points_mm) < 2:
        return 0.0
    step = max(1, len(points_mm) // sample)
    d, _ = cKDTree(points_mm).query(points_mm[::step], k=2)
    return float(np.median(d[:, 1]))


def _axis_label(direction: np.ndarray) -> tuple[str, float]:
    """(label, sign) of an image axis: the part axis it runs along when it is one, so ticks read as part
    coordinates (mm, frame F); else a view-plane axis."""
    k = int(np.argmax(np.abs(direction)))
    if abs(direction[k]) > 1 - 1e-9:
        return f"{'xyz'[k]}, mm", float(np.sign(direction[k]))
    return "view plane, mm", 1.0


@dataclass(frozen=True)
class Callout:
    """A label drawn with a leader at a point of the part (frame F, mm) on the colour maps."""

    label: str
    point_mm: tuple[float, float, float]
    colour: str = "black"


def visible_callouts(surface: CadSurface, view: View, width_px: int, callouts: Sequence[Callout],
                     margin_mm: float = 5.0) -> list[Callout]:
    """The callouts whose points the view sees: inside the picture and no more than ``margin_mm`` behind
    the first CAD surface on their pixel."""
    if not callouts:
        return []
    bg = _background(surface, view, width_px)
    x0, _, _, y1 = bg.extent_mm
    p = np.array([c.point_mm for c in callouts], float)
    col = np.floor((p @ bg.r - x0) / bg.px).astype(np.int64)
    row = np.floor((y1 - p @ bg.u) / bg.px).astype(np.int64)
    h, w = bg.t_hit.shape
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    depth = p @ bg.f - bg.depth0
    return [c for c, ok, cc, rr, dd in zip(callouts, inside, col, row, depth, strict=True)
            if ok and dd <= bg.t_hit[rr, cc] + margin_mm]


def deviation_norm(lower_mm: float, upper_mm: float, limit_mm: float | None = None) -> Normalize:
    """Symmetric colour scale: +/- ``limit_mm``, default three times the wider tolerance."""
    lim = limit_mm or 3.0 * max(abs(lower_mm), abs(upper_mm), 1e-6)
    return Normalize(-lim, lim, clip=True)


def deviation_map_png(
    surface: CadSurface,
    drawn: MapPoints,
    view: View,
    scale: ColourScale,
    width_px: int = 900,
    title: str | None = None,
    callouts: Sequence[Callout] = (),
) -> bytes:
    """One deviation colour map as PNG: the view, mm axes on the view plane, a colour bar with the band
    (``scale.marks``), and a labelled leader to each of ``callouts`` this view sees. Fixed axes positions (no
    layout engine: text measuring would cost more than the picture). Another ``scale`` draws another field per
    point (the uncertainty map)."""
    norm = scale.norm
    img = render_view(surface, drawn, view, norm, width_px, scale.cmap)
    h, w = img.rgb.shape[:2]
    fig_w, left, right, bottom, top = 8.0, 0.85, 1.3, 0.6, 0.45  # inches
    fig_h = bottom + top + (fig_w - left - right) * h / w
    fig = Figure(figsize=(fig_w, fig_h), dpi=110)
    ax = fig.add_axes((left / fig_w, bottom / fig_h, 1 - (left + right) / fig_w, 1 - (bottom + top) / fig_h))
    cax = fig.add_axes((1 - 0.95 / fig_w, bottom / fig_h, 0.18 / fig_w, 1 - (bottom + top) / fig_h))
    _, r, u = _camera(view)
    (xl, x_sign), (yl, y_sign) = _axis_label(r), _axis_label(u)
    x0, x1, y0, y1 = img.extent_mm
    ax.imshow(img.rgb, extent=(x_sign * x0, x_sign * x1, y_sign * y0, y_sign * y1), interpolation="nearest")
    ax.set_title(title or f"Deviation from CAD, {view.name}")
    ax.set_xlabel(xl)
    ax.set_ylabel(yl)
    for c in visible_callouts(surface, view, width_px, callouts):
        at = np.asarray(c.point_mm, float)
        ax.annotate(c.label, (x_sign * float(at @ r), y_sign * float(at @ u)), xytext=(18, 18),
                    textcoords="offset points", fontsize=9, fontweight="bold", color=c.colour,
                    bbox={"boxstyle": "round,pad=0.2", "fc": "white", "ec": c.colour, "lw": 1.0},
                    arrowprops={"arrowstyle": "-", "color": c.colour, "lw": 1.2})
    bar = fig.colorbar(ScalarMappable(norm, scale.cmap), cax=cax, label=scale.label)
    for v in scale.marks:
        bar.ax.axhline(v, color="black", lw=1.2)
    return png_bytes(fig)


MEASURED_RGB = np.array([0.20, 0.62, 0.30])  # coverage map: CAD surface with a cloud point on it
NOT_MEASURED_RGB = np.array([0.85, 0.25, 0.20])  # and without
MEASURED_WITHIN_MM = 1.0  # a triangle counts as measured when a cloud point lies this close to it


def measured_triangles(surface: CadSurface, points_mm: np.ndarray | None = None, *,
                       triangle_ids: np.ndarray | None = None, signed_mm: np.ndarray | None = None) -> np.ndarray:
    """``(T,)`` bool per CAD triangle: some point of the cloud (frame F, mm) lies within
    ``MEASURED_WITHIN_MM`` of it (closest triangle). The points' closest triangles and signed distances
    may be given instead (an inspection has them: no second query)."""
    if triangle_ids is None or signed_mm is None:
        closest = surface.closest(np.asarray(points_mm, float))
        triangle_ids, signed_mm = closest.triangle_ids, closest.signed_mm
    measured = np.zeros(len(surface.mesh.triangles), bool)
    measured[np.asarray(triangle_ids)[np.abs(signed_mm) <= MEASURED_WITHIN_MM]] = True
    return measured


def coverage_map_png(surface: CadSurface, points_mm: np.ndarray | None, view: View, width_px: int = 900,
                     measured: np.ndarray | None = None) -> bytes:
    """The CAD surface seen along ``view``, each triangle green where the cloud (frame F, mm) measured it
    (:func:`measured_triangles`, or ``measured`` as it returns) and red where it did not, shaded as the
    deviation maps; the title gives the measured share of the mesh area (docs/inspection-method.md, "Method")."""
    if measured is None:
        measured = measured_triangles(surface, points_mm)
    v = np.asarray(surface.mesh.vertices)[np.asarray(surface.mesh.triangles)]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    share = 100.0 * float(area[measured].sum() / max(area.sum(), 1e-12))
    bg = _background(surface, view, width_px)
    ids = bg.triangle_ids
    on_mesh = ids != o3d.t.geometry.RaycastingScene.INVALID_ID
    shade = bg.rgb[..., :1] / 0.82  # the grey background's lighting, 0.35-0.9
    colour = np.where(measured[np.where(on_mesh, ids, 0)][..., None], MEASURED_RGB, NOT_MEASURED_RGB)
    rgb = np.where(on_mesh[..., None], np.clip(shade * colour, 0.0, 1.0), bg.rgb)
    h, w = rgb.shape[:2]
    fig_w, left, right, bottom, top = 8.0, 0.85, 0.3, 0.6, 0.7  # inches
    fig = Figure(figsize=(fig_w, bottom + top + (fig_w - left - right) * h / w), dpi=110)
    ax = fig.add_axes((left / fig_w, bottom / fig.get_figheight(), 1 - (left + right) / fig_w,
                       1 - (bottom + top) / fig.get_figheight()))
    _, r, u = _camera(view)
    (xl, x_sign), (yl, y_sign) = _axis_label(r), _axis_label(u)
    x0, x1, y0, y1 = bg.extent_mm
    ax.imshow(rgb, extent=(x_sign * x0, x_sign * x1, y_sign * y0, y_sign * y1), interpolation="nearest")
    ax.set_title(f"Coverage of the CAD surface, {view.name}\n{share:.1f} % of its area measured "
                 "(green measured, red not)", fontsize=11)  # two lines: whole at any view name
    ax.set_xlabel(xl)
    ax.set_ylabel(yl)
    return png_bytes(fig)


def histogram_png(
    deviations_mm: np.ndarray, stats: DeviationStats, tolerance: ToleranceResult, norm: Normalize
) -> bytes:
    """Histogram of deviations (percent of points per bin) with the tolerance band and the shares in/out."""
    d = np.asarray(deviations_mm, float)
    tails = np.percentile(d, [0.1, 99.9])
    lo = min(float(tails[0]), 1.5 * tolerance.lower_mm)
    hi = max(float(tails[1]), 1.5 * tolerance.upper_mm)
    counts, edges = np.histogram(np.clip(d, lo, hi), bins=80, range=(lo, hi))
    centres = 0.5 * (edges[:-1] + edges[1:])
    fig = Figure(figsize=(8.0, 4.2), dpi=110)  # fixed axes, as the maps: no layout engine
    ax = fig.add_axes((0.09, 0.12, 0.89, 0.8))
    ax.axvspan(tolerance.lower_mm, tolerance.upper_mm, color="#2fbf4a", alpha=0.12, label="tolerance band")
    ax.bar(centres, 100.0 * counts / d.size, width=np.diff(edges), color=DEVIATION_CMAP(norm(centres)),
           edgecolor="none")
    for v in (tolerance.lower_mm, tolerance.upper_mm):
        ax.axvline(v, color="black", lw=1.0, ls="--")
    ax.axvline(stats.mean_mm, color="#444444", lw=1.0, label=f"mean {stats.mean_mm:+.4f} mm")
    ax.set_xlabel("deviation from CAD, mm (+ = material above the surface)")
    ax.set_ylabel("points, %")
    ax.set_title(
        f"{tolerance.in_pct:.2f} % in [{tolerance.lower_mm:+.3f}, {tolerance.upper_mm:+.3f}] mm, "
        f"{tolerance.above_pct:.2f} % above, {tolerance.below_pct:.2f} % below"
    )
    ax.legend(loc="upper right", fontsize=8)
    return png_bytes(fig)
