"""Report: colour maps show the right colours where the part is seen, the stitching view measures layering,
report.html is self-contained and report.json carries the same numbers."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest
from tandemscan.config.models import InspectionConfig
from tandemscan.pipeline.inspection.deviation_maps import (
    DEVIATION_CMAP,
    MapPoints,
    View,
    coverage_map_png,
    deviation_norm,
    measured_triangles,
    render_view,
)
from tandemscan.pipeline.inspection.inspect import CadSurface, InspectionCriteria, inspect_cloud
from tandemscan.pipeline.inspection.report import (
    InspectedPart,
    ReportFacts,
    ReportStyle,
    StitchViews,
    build_report,
    write_report,
)
from tandemscan.pipeline.inspection.stitch_quality import overlap_quality


def grid_on_face(z_mm, size=(400.0, 200.0), step=2.0):
    x, y = np.meshgrid(np.arange(1, size[0], step), np.arange(1, size[1], step))
    return np.c_[x.ravel(), y.ravel(), np.full(x.size, z_mm)]


@pytest.fixture(scope="module")
def box():
    return CadSurface(o3d.geometry.TriangleMesh.create_box(400.0, 200.0, 100.0))


def test_colour_map_paints_visible_points_only(box):
    top = grid_on_face(100.3)  # 0.3 mm above the top face: saturated red
    bottom = grid_on_face(-0.3)  # 0.3 mm below the bottom face, hidden from above: would be blue
    pts = np.vstack([top, bottom])
    vals = np.r_[np.full(len(top), 0.3), np.full(len(bottom), -0.3)]
    norm = deviation_norm(-0.1, 0.1)
    img = render_view(box, MapPoints(pts, vals), View("top", (0, 0, -1), up=(0, 1, 0)), norm, width_px=300)
    red, blue = DEVIATION_CMAP(norm(0.3))[:3], DEVIATION_CMAP(norm(-0.3))[:3]
    flat = img.rgb.reshape(-1, 3)
    n_red = np.all(np.isclose(flat, red, atol=1e-6), axis=1).sum()
    px_mm = (img.extent_mm[1] - img.extent_mm[0]) / 300
    assert n_red == img.coloured_px > 0.9 * (400 * 200) / px_mm**2  # the top face is covered, in red
    assert not np.all(np.isclose(flat, blue, atol=1e-6), axis=1).any()
    # seen from below, the same cloud is blue and the red layer is hidden
    img = render_view(box, MapPoints(pts, vals), View("bottom", (0, 0, 1), up=(0, 1, 0)), norm, width_px=300)
    flat = img.rgb.reshape(-1, 3)
    assert np.all(np.isclose(flat, blue, atol=1e-6), axis=1).sum() == img.coloured_px > 0
    assert not np.all(np.isclose(flat, red, atol=1e-6), axis=1).any()


def test_coverage_map_tells_measured_from_not_measured():
    box = CadSurface(o3d.geometry.TriangleMesh.create_box(400.0, 200.0, 100.0).subdivide_midpoint(3))
    half = grid_on_face(100.2, size=(199.0, 200.0))  # the top face's left half (x < 200 mm), 0.2 mm above it
    measured = measured_triangles(box, half)
    v = np.asarray(box.mesh.vertices)[np.asarray(box.mesh.triangles)]
    top = np.all(np.isclose(v[:, :, 2], 100.0), axis=1)
    centre_x = v[:, :, 0].mean(axis=1)
    assert np.array_equal(measured, top & (centre_x < 200.0))  # the top's left half, nothing else
    assert not measured_triangles(box, half + [0.0, 0.0, 5.0]).any()  # 5 mm off the surface: not measured
    png = coverage_map_png(box, half, View("top", (0, 0, -1), up=(0, 1, 0)), width_px=300)
    rgb = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[..., ::-1].astype(int)
    green = (rgb[..., 1] > rgb[..., 0] + 40) & (rgb[..., 1] > rgb[..., 2] + 40)
    red = (rgb[..., 0] > rgb[..., 1] + 60) & (rgb[..., 0] > rgb[..., 2] + 60)
    assert green.sum() > 1000 and red.sum() > 1000
    assert abs(green.sum() - red.sum()) < 0.1 * green.sum()  # seen from above: half green, half red


def layered_scans(offset_mm):
    """Three overlapping patches of the top face; the middle one lifted by ``offset_mm``."""
    rng = np.random.default_rng(0)
    scans = []
    for k in range(3):
        p = np.c_[rng.uniform(100 * k, 100 * k + 150, 3000), rng.uniform(0, 150, 3000), np.full(3000, 100.0)]
        p[:, 2] += rng.normal(0, 0.01, 3000) + (offset_mm if k == 1 else 0.0)
        scans.append(p)
    return scans


def test_overlap_quality_sees_the_layering_before_and_not_after():
    before, after = layered_scans(0.2), layered_scans(0.0)
    pairs = overlap_quality(before, after)
    assert [(p.i, p.j) for p in pairs] == [(0, 1), (1, 2)]
    for p in pairs:
        assert p.points > 500
        assert p.rms_before_mm == pytest.approx(0.2, abs=0.02)
        assert p.rms_after_mm < 0.03
    with pytest.raises(ValueError, match="3 scans before"):
        overlap_quality(before, after[:2])


def make_report(box, tmp_path):
    rng = np.random.default_rng(3)
    pts = np.vstack([grid_on_face(100.0, step=3.0), grid_on_face(0.0, step=3.0)])
    pts[:, 2] += 0.08 * np.sin(pts[:, 0] / 40.0) + rng.normal(0, 0.01, len(pts))
    cfg = InspectionConfig(map_width_px=400)
    result = inspect_cloud(pts, box, InspectionCriteria.from_section(cfg))
    views = (View("isometric", (-1.0, 1.0, -0.8)), View("top (from +z)", (0, 0, -1), up=(0, 1, 0)))
    facts = ReportFacts("Box <test>", {"cloud": "cloud.ply", "cad": "box.stl"},
                        {"stitched RMS vs CAD, mm": 0.0123, "scans": 3})
    report = build_report(result, InspectedPart(box), ReportStyle.from_section(cfg, views=views), facts,
                          stitching=StitchViews(layered_scans(0.2), layered_scans(0.0)))
    return result, report, write_report(report, tmp_path)


@pytest.fixture(scope="module")
def written(box, tmp_path_factory):
    """One report, shared by the content test and the browser test (rendering takes seconds)."""
    out = tmp_path_factory.mktemp("report")
    return (out, *make_report(box, out))


def test_report_html_self_contained_and_json_same_numbers(written):
    tmp_path, result, report, (html_path, json_path) = written
    html = html_path.read_text()
    assert "Box &lt;test&gt;" in html  # escaped
    assert not re.search(r"""(src|href)=["'](https?:|//|file:)""", html)  # nothing fetched from outside
    images = re.findall(r'src="data:image/png;base64,', html)
    names = [f["name"] for f in report.data["figures"]]
    assert len(images) == len(names) == 2 + 1 + 2 + 1 + 1  # views, coverage, upper/lower, histogram, stitching
    assert "coverage" in names
    for table in ("stats", "tolerance", "bestfit", "accuracy", "stitching", "meta"):
        assert f'id="{table}"' in html
    assert f"{result.stats.mean_mm:+.4f}" in html and f"{result.tolerance.in_pct:.2f}" in html
    data = json.loads(json_path.read_text())["inspection"]
    assert data["as_measured"]["stats"]["rms_mm"] == result.stats.rms_mm
    assert data["as_measured"]["tolerance"]["in_pct"] == result.tolerance.in_pct
    assert data["accuracy"]["scans"] == 3 and len(data["stitching"]) == 2
    assert np.asarray(data["best_fit"]["T_F_M"]).shape == (4, 4)
    for f in data["figures"]:
        assert (tmp_path / f["file"]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--hide-scrollbars", "--enable-logging=stderr", "--window-size=1280,2200",
]


@pytest.mark.browser
@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (make system-deps installs it)")
def test_report_renders_in_headless_chromium(written, tmp_path):
    html_path = written[3][0]
    shot = tmp_path / "shot.png"
    proc = subprocess.run(
        [CHROMIUM, *CHROMIUM_FLAGS, f"--user-data-dir={tmp_path / 'profile'}", f"--screenshot={shot}",
         html_path.as_uri()],
        capture_output=True, text=True, timeout=180,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "CONSOLE" not in proc.stderr and "Uncaught" not in proc.stderr  # no page errors
    img = cv2.imread(str(shot), cv2.IMREAD_COLOR)
    assert img is not None and img.shape[0] >= 1000 and img.shape[1] == 1280
    not_white = np.any(img < 245, axis=2).mean()
    hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV)
    colourful = ((hsv[..., 1] > 120) & (hsv[..., 2] > 80)).mean()  # the colour maps decoded and drawn
    assert not_white > 0.05 and colourful > 0.01 and img.std() > 20
    if os.environ.get("TANDEMSCAN_SCREENSHOTS"):  # TANDEMSCAN_SCREENSHOTS=docs make test refreshes docs/'s picture
        shutil.copyfile(shot, Path(os.environ["TANDEMSCAN_SCREENSHOTS"]) / "inspection-report.png")


def test_isometric_view_looks_at_the_measured_side():
    from tandemscan.pipeline.inspection.deviation_maps import STANDARD_VIEWS, facing_isometric

    v = facing_isometric(np.tile([0.0, 1.0, 0.2], (50, 1)))  # surface facing +y (and a little up)
    assert v.forward[1] < 0 and v.forward[2] < 0 and abs(v.forward[0]) < 1e-12  # eye at +y, above
    assert facing_isometric(np.array([[1.0, 0, 0], [-1.0, 0, 0]])) == STANDARD_VIEWS["isometric"]


def test_the_stitching_figure_drawn_beside_the_inspection_is_the_one_the_report_would_draw_and_takes(box):
    """:meth:`StitchViews.drawn` draws the stitching figure on a thread of its own once the overlap is known: the
    bytes the report would draw from the same views; the report takes the figure so drawn instead of drawing it."""
    import dataclasses
    from concurrent.futures import Future

    from tandemscan.pipeline.inspection.stitch_quality import stitching_png

    views = StitchViews(layered_scans(0.2), layered_scans(0.0)).drawn()
    assert views.overlap is not None and views.figure is not None and views.drawn() is views
    png = views.figure.result(timeout=60.0)
    assert png == stitching_png(views.before, views.after, overlap_quality(views.before, views.after))
    drawn = Future()
    drawn.set_result(png + b"drawn beside")  # what the report shows is what was drawn beside, not drawn again
    result = inspect_cloud(grid_on_face(100.0, step=4.0), box, InspectionCriteria.from_section(InspectionConfig()))
    style = ReportStyle.from_section(InspectionConfig(map_width_px=200), views=(View("top", (0, 0, -1), up=(0, 1, 0)),))
    report = build_report(result, InspectedPart(box), style, stitching=dataclasses.replace(views, figure=drawn))
    assert next(f for f in report.figures if f.name == "stitching").png == png + b"drawn beside"
