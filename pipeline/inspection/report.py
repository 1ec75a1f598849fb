"""The inspection report: figures and numbers of an :class:`InspectionResult`, written as a self-contained
``report.html`` (images embedded as data URIs, jinja2 template shipped with the package) and a
``report.json`` with the same figures (numbers, plus the PNGs under ``figures/``). Millimetres, degrees.
"""

from __future__ import annotations

import base64
import dataclasses
import datetime as dt
import json
import logging
from collections.abc import Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

import jinja2
import numpy as np
from matplotlib import colormaps
from matplotlib.colors import Normalize
from tandemscan.pipeline.inspection.alignment import Alignment
from tandemscan.pipeline.inspection.characteristic_figures import (
    CloseUp,
    Surroundings,
    closeup,
    section_png,
    trend_png,
)
from tandemscan.pipeline.inspection.characteristics import CharacteristicResult
from tandemscan.pipeline.inspection.deviation_maps import (
    STANDARD_VIEWS,
    Callout,
    ColourScale,
    MapPoints,
    View,
    coverage_map_png,
    deviation_map_png,
    deviation_norm,
    facing_isometric,
    histogram_png,
    measured_triangles,
    typical_spacing,
)
from tandemscan.pipeline.inspection.inspect import CadSurface, InspectionResult
from tandemscan.pipeline.inspection.spc import individuals_chart
from tandemscan.pipeline.inspection.stitch_quality import PAIR_SAMPLE, overlap_quality, stitching_png
from tandemscan.pipeline.io.durable import write_durably
from tandemscan.pipeline.parameters import FromSection
from tandemscan.pipeline.planning.coverage import CoverageFigures

if TYPE_CHECKING:
    from tandemscan.config.inspection_template import InspectionTemplate

log = logging.getLogger(__name__)

TEMPLATE = "report.html.j2"
FAILED_TEMPLATE = "report_failed.html.j2"  # an inspection whose alignment failed


@dataclass(frozen=True)
class ReportStyle(FromSection):
    """How the report draws: ``[inspection]``'s keys of the same names (``ReportStyle.from_section(cfg)``). The
    colour maps saturate at +/- ``colour_limit_mm`` (None: 3x the wider tolerance), are ``map_width_px`` wide and
    draw an even subsample of at most ``map_max_points``; ``views`` by name (``STANDARD_VIEWS``; "isometric" looks
    at the measured side) or as a :class:`View`."""

    colour_limit_mm: float | None
    map_width_px: int
    map_max_points: int
    views: tuple[str | View, ...]


@dataclass(frozen=True)
class InspectedPart:
    """The part a cloud is inspected against: its CAD ``surface`` (frame F, mm), its inspection ``template``
    (characteristics; None: none), ``labels`` (part number, serial, template file and measuring system, as the
    report and results.qif name them) and ``history`` (per characteristic id the part's earlier serials' results,
    ``serial`` and ``actual_mm``, oldest first)."""

    surface: CadSurface
    template: InspectionTemplate | None = None
    labels: Mapping[str, str] = field(default_factory=dict)
    history: Mapping[str, Sequence[Mapping]] = field(default_factory=dict)


@dataclass(frozen=True)
class StitchViews:
    """The stitching-quality view's inputs: each scan's points (mm, the frame of the cloud they go with) in
    measuring order ``before`` and ``after`` the correction (None: not corrected), their :func:`overlap_quality`
    where it is being computed already (``overlap``, a future) and their figure (:func:`stitching_png`) where it is
    being drawn already (``figure``, a future)."""

    before: Sequence[np.ndarray]
    after: Sequence[np.ndarray] | None = None
    overlap: Future | None = None
    figure: Future | None = None

    def started(self) -> StitchViews:
        """These views with their overlap being computed (on a thread of its own where it was not yet)."""
        if self.overlap is not None:
            return self
        return dataclasses.replace(self, overlap=in_background(overlap_quality, self.before, self.after))

    def drawn(self) -> StitchViews:
        """These views (:meth:`started`) with their figure being drawn on a thread of its own once their overlap is
        known, beside the inspection (the report takes it drawn: a whole part's 368 pairs' bars and its section
        are about 2 s of one core)."""
        views = self.started()
        if views.figure is not None:
            return views
        return dataclasses.replace(views, figure=in_background(_stitching_figure, views))


def _stitching_figure(views: StitchViews) -> bytes | None:
    """:func:`stitching_png` of ``views`` (their overlap waited for)."""
    assert views.overlap is not None
    return stitching_png(views.before, views.after, views.overlap.result())


@dataclass(frozen=True)
class ReportFacts:
    """What the report states beside the inspection: its ``title``, ``meta`` (the job, cloud and CAD files),
    ``accuracy`` (figures computed elsewhere: pose errors against ground truth, calibration residuals) and
    ``coverage`` (what the job's plan covers and leaves out, reported with the share of it the cloud measured)."""

    title: str = "Inspection report"
    meta: Mapping[str, str] = field(default_factory=dict)
    accuracy: Mapping[str, float | int | str] = field(default_factory=dict)
    coverage: CoverageFigures | None = None


@dataclass(frozen=True)
class ReportFigure:
    """One picture of the report: a file-safe name, a caption and the PNG bytes."""

    name: str
    caption: str
    png: bytes = field(repr=False)

    def data_uri(self) -> str:
        """The PNG as a ``data:`` URI for embedding."""
        return "data:image/png;base64," + base64.b64encode(self.png).decode("ascii")


@dataclass(frozen=True)
class Report:
    """Everything that goes into report.html and report.json."""

    data: dict
    figures: tuple[ReportFigure, ...]


def _plain(obj):
    """Dataclasses and numpy values as JSON-ready Python values."""
    if dataclasses.is_dataclass(obj):
        return {f.name: _plain(getattr(obj, f.name)) for f in dataclasses.fields(obj) if f.repr}
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Mapping):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_plain(v) for v in obj]
    return obj


NO_ALIGNMENT = {"method": "none", "residual_mm": 0.0, "start": "the cloud as given, in the CAD frame",
                "spheres": [], "missing_spheres": []}
SIDE_COLOURS = {"upper": "#b3140d", "lower": "#1d3fbf"}


def inspection_summary(result: InspectionResult, alignment: Alignment | None = None) -> dict:
    """The numbers of an inspection as JSON-ready dicts (verdict, alignment, deviation areas largest
    extreme first, as measured, per region, best fit), mm / deg."""
    out = {
        "verdict": result.verdict,
        "alignment": alignment.summary() if alignment is not None else dict(NO_ALIGNMENT),
        "deviations": [_plain(a) for a in result.areas],
        "as_measured": {"stats": _plain(result.stats), "tolerance": _plain(result.tolerance)},
        "regions": [_plain(r) for r in result.regions],
        "best_fit": _plain(result.best_fit),
        "best_fit_note": result.best_fit_note,
    }
    j = result.judgement
    if j is not None:  # the decision rule's verdict (docs/verdict.md, "Verdict")
        out |= {"verdict_reasons": list(j.reasons), "decision_rule": j.rule.as_dict(),
                "decision_rule_label": j.rule.label, "uncertainty": j.uncertainty.summary(),
                "region_verdicts": [_plain(r) for r in j.regions],
                "installation": _plain(j.context.installation), "verification": _plain(j.context.verification)}
    return out


def build_report(
    result: InspectionResult,
    part: InspectedPart,
    style: ReportStyle,
    facts: ReportFacts = ReportFacts(),
    *,
    alignment: Alignment | None = None,
    stitching: StitchViews | None = None,
    characteristics: Sequence[CharacteristicResult] | Future = (),
    surroundings: Mapping[int, Surroundings] | None = None,
) -> Report:
    """Render the figures and collect the numbers of one inspection of ``part``, drawn as ``style`` says, with
    ``facts`` beside them. ``alignment`` is how the cloud was placed in the CAD frame (none: it came in that
    frame); ``stitching``: the scans before and after the correction, for the stitching-quality view;
    ``characteristics``: the template's, evaluated (:mod:`tandemscan.pipeline.inspection.characteristics`), which
    the report leads with (or their future, waited for once the maps are drawn), with the trend over the part's
    serials (``part.history``) of those that fail or drift. The deviation areas are labelled on every map
    (``#id`` at the centroid); each of the largest has a close-up drawn from ``result``'s points, or from its
    ``surroundings`` by area id where given (a tiled cloud's points around it at full density).

    Eight parameters: the inspection and its part, how it is drawn and its facts (what every report has), and four
    optional views of it, keyword-only: its alignment, its stitching, its characteristics and its close-ups'
    surroundings."""
    surface = part.surface
    if stitching is not None:
        stitching = stitching.started()
    tol = result.tolerance
    norm = deviation_norm(tol.lower_mm, tol.upper_mm, style.colour_limit_mm)
    every = max(1, int(np.ceil(len(result.points_mm) / style.map_max_points)))  # pictures only; numbers use all
    p, d, n = result.points_mm[::every], result.deviations_mm[::every], result.cad_normals[::every]
    views = [v if isinstance(v, View) else facing_isometric(n) if v == "isometric" else STANDARD_VIEWS[v]
             for v in style.views]  # the isometric view looks at the side that was measured
    drawn = MapPoints(p, d, n, typical_spacing(p))
    scale = ColourScale(norm, (tol.lower_mm, tol.upper_mm))
    callouts = [Callout(f"#{a.id}", a.centroid_mm, SIDE_COLOURS[a.side]) for a in result.areas]
    maps, split, uncertainty = [], [], []
    measured = _measured(result, surface)
    for i, view in enumerate(views):
        png = deviation_map_png(surface, drawn, view, scale, style.map_width_px, callouts=callouts)
        maps.append(ReportFigure(f"map-{i}", f"Deviation colour map, {view.name}", png))
        if i > 0:
            continue
        coverage_map = _coverage_figure(result, surface, view, style, measured)  # the first view's picture cached
        uncertainty = _uncertainty_map(result, surface, view, style, drawn, every)
        for label, side, keep in (("upper", "above", d > 0), ("lower", "below", d < 0)):  # first view only
            if keep.any():
                title_ = f"{label.capitalize()} deviation (points {side} CAD), {view.name}"
                ours = [c for c, a in zip(callouts, result.areas, strict=True) if a.side == label]
                png = deviation_map_png(surface, drawn.subset(keep), view, scale, style.map_width_px, title_, ours)
                split.append(ReportFigure(f"{label}-deviation", title_, png))
    if isinstance(characteristics, Future):  # evaluated while the maps were drawn
        characteristics = characteristics.result()
    trends = trend_figures(characteristics, part.history, part.labels)
    quality = quality_figures(result, characteristics, tol, norm, surroundings or {}) + [f for f, _ in trends]
    figures = quality + maps + uncertainty + [coverage_map] + split
    hist = histogram_png(result.deviations_mm, result.stats, tol, norm)
    caption = "Deviation histogram with the tolerance band (the outer bins collect the 0.1 % tails)"
    figures.append(ReportFigure("histogram", caption, hist))
    pairs = []
    if stitching is not None:
        assert stitching.overlap is not None
        pairs = stitching.overlap.result()
        png = _stitching_figure(stitching) if stitching.figure is None else stitching.figure.result()
        if png is not None:
            caption = ("Overlap of neighbouring scans before and after correction (RMS of an even subsample of "
                       f"at most {PAIR_SAMPLE} overlap points a pair)")
            figures.append(ReportFigure("stitching", caption, png))
    data = {
        "title": facts.title,
        "created_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "units": {"length": "mm", "angle": "deg", "deviation_sign": "+ = above the CAD surface (outward normal)"},
        "meta": dict(facts.meta),
        "colour_scale_mm": [norm.vmin, norm.vmax],
        **inspection_summary(result, alignment),
        "part": dict(part.labels),
        "characteristics": [c.summary() for c in characteristics],
        "trends": [t for _, t in trends],
        **({} if facts.coverage is None
           else {"coverage": facts.coverage.with_measured(surface.mesh, measured).as_dict()}),
        "closeups": [dict(c.summary(), figure=f"figures/closeup-{c.area_id}.png") for c in closeups_of(quality)],
        "accuracy": _plain(dict(facts.accuracy)),
        "stitching": [_plain(pr) for pr in pairs],
        "figures": [{"name": f.name, "caption": f.caption, "file": f"figures/{f.name}.png"} for f in figures],
    }
    return Report(data, tuple(figures))


MAX_CLOSEUPS = 12  # close-ups of the largest deviation areas; the maps label the others


@dataclass(frozen=True)
class CloseUpFigure(ReportFigure):
    """A deviation area's close-up as a report figure, with what it shows."""

    closeup: CloseUp | None = field(default=None, repr=False)


def quality_figures(result: InspectionResult, characteristics: Sequence[CharacteristicResult], tol, norm,
                    surroundings: Mapping[int, Surroundings]) -> list[ReportFigure]:
    """The figures the report leads with: each section's curve with its band, then a close-up of each of
    the :data:`MAX_CLOSEUPS` largest deviation areas with its surroundings (by area id, else the result's points)."""
    out: list[ReportFigure] = [
        ReportFigure(f"section-{c.id}", f"{c.id} {c.name}: deviation along the CAD section with the band",
                     section_png(c))
        for c in characteristics if c.curve is not None and len(c.curve.arc_mm)]
    everywhere = Surroundings(result.points_mm, result.deviations_mm, result.cad_normals)
    for a in result.areas[:MAX_CLOSEUPS]:
        c = closeup(a, surroundings.get(a.id, everywhere), tol.lower_mm, tol.upper_mm, norm)
        out.append(CloseUpFigure(f"closeup-{a.id}", f"Close-up of deviation area #{a.id} and its surroundings "
                                 f"({c.points} points, {c.beyond_band} beyond the band)", c.png, c))
    return out


def trend_figures(characteristics: Sequence[CharacteristicResult], history: Mapping[str, Sequence[Mapping]],
                  part: Mapping[str, str]) -> list[tuple[ReportFigure, dict]]:
    """(figure, figures) of the trend over serials of each characteristic that fails or whose individuals
    chart, with this inspection's value last, drifts (:func:`individuals_chart`)."""
    out = []
    for c in characteristics:
        earlier = [h for h in history.get(c.id, ()) if h.get("actual_mm") is not None]
        if not earlier or not np.isfinite(c.actual_mm):
            continue
        chart = individuals_chart([h["actual_mm"] for h in earlier] + [c.actual_mm], c.lower_mm, c.upper_mm)
        if c.status != "fail" and not chart.drift:
            continue
        serials = [str(h.get("serial") or "?") for h in earlier] + [str(part.get("serial") or "this")]
        figure = ReportFigure(f"trend-{c.id}", f"{c.id} {c.name}: trend over {len(serials)} serials", trend_png(
            c, serials, chart))
        out.append((figure, {"id": c.id, "serials": serials} | chart.summary()))
    return out


def closeups_of(figures: Sequence[ReportFigure]) -> list[CloseUp]:
    """The close-ups among ``figures``."""
    return [f.closeup for f in figures if isinstance(f, CloseUpFigure) and f.closeup is not None]


def _uncertainty_map(result: InspectionResult, surface: CadSurface, view: View, style: ReportStyle,
                     deviations: MapPoints, every: int) -> list[ReportFigure]:
    """The points' expanded uncertainty U on the first view (none where every U is 0), at the points the
    deviation maps drew (``deviations``, every ``every``-th of the result's): viridis from 0 to the larger of its
    99th percentile and a quarter of the tolerance width; the bar marks where the test uncertainty ratio is 4:1
    (U = width / 8)."""
    j = result.judgement
    if j is None or not np.any(j.uncertainty.expanded_mm > 0.0):
        return []
    U = j.uncertainty.expanded_mm[::every]
    width = result.tolerance.upper_mm - result.tolerance.lower_mm
    norm = Normalize(0.0, max(float(np.percentile(U, 99)), 0.25 * width))
    scale = ColourScale(norm, (width / 8.0,), colormaps["viridis"], f"U (k = {j.rule.k:g}), mm; line: TUR 4:1")
    title = f"Expanded uncertainty U (k = {j.rule.k:g}) of the deviation, {view.name}"
    png = deviation_map_png(surface, dataclasses.replace(deviations, values=U), view, scale, style.map_width_px,
                            title)
    return [ReportFigure("uncertainty-map", title, png)]


def in_background(fn, *args) -> Future:
    """``fn(*args)`` on a thread of its own (KD-tree queries and numpy let the caller's figures draw)."""
    pool = ThreadPoolExecutor(1, thread_name_prefix=fn.__name__)
    try:
        return pool.submit(fn, *args)
    finally:
        pool.shutdown(wait=False)  # the thread ends with its one task


def _measured(result: InspectionResult, surface: CadSurface) -> np.ndarray:
    """Per CAD triangle: the cloud measured it (``measured_triangles``)."""
    if result.triangle_ids is None:
        return measured_triangles(surface, result.points_mm)
    return measured_triangles(surface, triangle_ids=result.triangle_ids, signed_mm=result.deviations_mm)


def _coverage_figure(result: InspectionResult, surface: CadSurface, view: View,
                     style: ReportStyle, measured: np.ndarray) -> ReportFigure:
    """The coverage map: measured (``measured``, per CAD triangle) vs not measured, in the first view."""
    png = coverage_map_png(surface, result.points_mm, view, style.map_width_px, measured)
    return ReportFigure("coverage", f"Coverage of the CAD surface (measured vs not measured), {view.name}", png)


def failed_report(reason: str, alignment: Alignment, *, title: str = "Inspection report",
                  meta: Mapping[str, str] | None = None) -> Report:
    """The report of a part that could not be inspected (its alignment to CAD failed): verdict
    "indeterminate", the reason, and the alignment that was tried; no figures."""
    return Report({"title": title, "created_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
                   "units": {"length": "mm", "angle": "deg"}, "meta": dict(meta or {}), "verdict": "indeterminate",
                   "reason": reason, "verdict_reasons": [reason], "alignment": alignment.summary(), "figures": []},
                  ())


def render_html(report: Report) -> str:
    """The report as one self-contained HTML page (a failed inspection's when its verdict is "indeterminate"
    with a reason)."""
    name = FAILED_TEMPLATE if "reason" in report.data else TEMPLATE
    source = (resources.files("tandemscan.pipeline.inspection") / "templates" / name).read_text(encoding="utf-8")
    env = jinja2.Environment(autoescape=True, undefined=jinja2.StrictUndefined, trim_blocks=True, lstrip_blocks=True)
    return env.from_string(source).render(r=report.data, figures=report.figures)


def write_report(
    report: Report, out_dir: Path | str, json_name: str | None = "report.json"
) -> tuple[Path, Path | None]:
    """Write ``report.html``, ``figures/*.png`` and (unless ``json_name`` is None, for a caller that merges
    ``report.data`` into its own JSON) the JSON, ``{"inspection": report.data}``, into ``out_dir``; returns
    (html, json or None). The HTML and the JSON are each written durably (a temporary file in the same folder,
    then renamed over the old one): a reader or a crash sees the old report or the whole new one, never half."""
    out = Path(out_dir)
    (out / "figures").mkdir(parents=True, exist_ok=True)
    for f in report.figures:
        (out / "figures" / f"{f.name}.png").write_bytes(f.png)
    html = out / "report.html"
    write_durably(html, lambda file: file.write(render_html(report).encode("utf-8")))
    js = None
    if json_name is not None:  # the same layout as a job's report.json: the numbers under "inspection"
        js = out / json_name
        text = json.dumps({"inspection": report.data}, indent=2) + "\n"
        write_durably(js, lambda file: file.write(text.encode("utf-8")))
    log.info("wrote %s%s", html, f" and {js}" if js else "")
    return html, js
