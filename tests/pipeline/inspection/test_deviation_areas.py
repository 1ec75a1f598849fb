"""Deviation areas: connected parts of the surface beyond the band, found on a noisy plane with a known dent
and bulge (centroid, area, extreme, side), none on noise alone; the verdict and the report show them."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from tandemscan.config.models import InspectionConfig
from tandemscan.pipeline.inspection.deviation_areas import DeviationCloud, find_deviation_areas
from tandemscan.pipeline.inspection.inspect import CadSurface, InspectionCriteria, inspect_cloud
from tandemscan.pipeline.inspection.report import InspectedPart, ReportStyle, build_report


def bell(points, centre, radius, depth):
    rho = np.linalg.norm(points[:, :2] - centre, axis=1) / radius
    return np.where(rho < 1.0, 0.5 * depth * (1.0 + np.cos(np.pi * np.clip(rho, 0, 1))), 0.0)


def plane(rng, noise=0.03, step=1.0):
    x, y = np.meshgrid(np.arange(0.0, 300.0, step), np.arange(0.0, 300.0, step))
    p = np.c_[x.ravel(), y.ravel(), np.zeros(x.size)]
    return p, rng.normal(0.0, noise, len(p))


def test_a_dent_and_a_bulge_are_two_areas_with_their_figures():
    rng = np.random.default_rng(0)
    p, d = plane(rng)
    d += -bell(p, (100.0, 100.0), 30.0, 0.3) + bell(p, (220.0, 200.0), 20.0, 0.2)
    areas = find_deviation_areas(DeviationCloud(p, d), -0.1, 0.1, smoothing_mm=4.0, min_area_mm2=50.0)
    assert [(a.id, a.side) for a in areas] == [(1, "lower"), (2, "upper")]  # largest |extreme| first
    dent, bulge = areas
    np.testing.assert_allclose(dent.centroid_mm, [100.0, 100.0, 0.0], atol=0.5)
    np.testing.assert_allclose(bulge.centroid_mm, [220.0, 200.0, 0.0], atol=0.5)
    # where the bell exceeds 0.1 mm: rho < acos(2 * 0.1 / depth - 1) / pi
    for a, r, depth in ((dent, 30.0, 0.3), (bulge, 20.0, 0.2)):
        r_band = r * np.arccos(2 * 0.1 / depth - 1) / np.pi
        assert a.area_mm2 == pytest.approx(np.pi * r_band**2, rel=0.1)
        assert abs(a.extreme_mm) == pytest.approx(depth, abs=0.02)
        assert abs(a.mean_mm) > 0.1 and a.points == pytest.approx(a.area_mm2, rel=0.15)  # 1 point per mm^2


def test_noise_alone_and_small_spots_give_no_area():
    rng = np.random.default_rng(1)
    p, d = plane(rng, noise=0.05)  # half the band: raw points leave it by the thousand
    assert (np.abs(d) > 0.1).sum() > 1000
    d += bell(p, (150.0, 150.0), 4.0, 0.3)  # a 0.3 mm spot of under 20 mm^2 beyond the band
    assert find_deviation_areas(DeviationCloud(p, d), -0.1, 0.1, smoothing_mm=4.0, min_area_mm2=50.0) == ()
    assert len(find_deviation_areas(DeviationCloud(p, d), -0.1, 0.1, smoothing_mm=2.0, min_area_mm2=5.0)) == 1


def test_verdict_and_report_list_the_areas_with_callouts():
    box = CadSurface(o3d.geometry.TriangleMesh.create_box(300.0, 300.0, 50.0))
    rng = np.random.default_rng(2)
    p, d = plane(rng, noise=0.01, step=1.5)
    p[:, 2] = 50.0
    ok = inspect_cloud(p, box, InspectionCriteria.from_section(InspectionConfig(best_fit=False)))
    assert ok.verdict == "pass" and ok.areas == ()
    p[:, 2] += bell(p, (120.0, 140.0), 30.0, 0.4)
    cfg = InspectionConfig(best_fit=False, map_width_px=300, views=("top",), regions=())
    result = inspect_cloud(p, box, InspectionCriteria.from_section(cfg))
    assert result.verdict == "fail" and [a.side for a in result.areas] == ["upper"]
    report = build_report(result, InspectedPart(box), ReportStyle.from_section(cfg))
    assert report.data["verdict"] == "fail" and report.data["alignment"]["method"] == "none"
    (area,) = report.data["deviations"]
    assert set(area) == {"id", "side", "centroid_mm", "area_mm2", "extreme_mm", "mean_mm", "points", "decision",
                         "uncertainty_mm", "reason"}
    np.testing.assert_allclose(area["centroid_mm"], [120.0, 140.0, 50.0], atol=1.0)
