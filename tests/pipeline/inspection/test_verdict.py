"""The verdict by the decision rule and the points' uncertainty: overall, per region, per deviation area
(pipeline/inspection/verdict.py)."""

import gc
import weakref

import numpy as np
import open3d as o3d
import pytest
from tandemscan.config.models import InspectionConfig, RegionConfig
from tandemscan.pipeline.inspection import deviation_areas
from tandemscan.pipeline.inspection import verdict as verdict_module
from tandemscan.pipeline.inspection.inspect import CadSurface, inspect_cloud
from tandemscan.pipeline.inspection.inspection_job import InspectionSettings
from tandemscan.pipeline.inspection.point_uncertainty import GivenUncertainty
from tandemscan.pipeline.inspection.verdict import VerdictContext, judge
from tandemscan.pipeline.io.cloud_io import read_ply_vertices

TOP = 50.0
BUMPS = {"out": ((100.0, 100.0), 0.8), "in": ((300.0, 200.0), 0.3), "between": ((500.0, 100.0), -0.54)}


@pytest.fixture(scope="module")
def box():
    return CadSurface(o3d.geometry.TriangleMesh.create_box(600.0, 300.0, TOP))


def bell(points, centre, radius, depth):
    rho = np.linalg.norm(points[:, :2] - centre, axis=1) / radius
    return np.where(rho < 1.0, 0.5 * depth * (1.0 + np.cos(np.pi * np.clip(rho, 0, 1))), 0.0)


def top_with_bumps(step=1.5):
    x, y = np.meshgrid(np.arange(2.0, 598.0, step), np.arange(2.0, 298.0, step))
    p = np.c_[x.ravel(), y.ravel(), np.full(x.size, TOP)]
    for centre, height in BUMPS.values():
        p[:, 2] += bell(p, centre, 30.0, height)
    return p


def cfg(**kw) -> InspectionSettings:
    regions = (RegionConfig(name="left", min_mm=(-1.0, -1.0, -1.0), max_mm=(200.0, 301.0, 100.0)),
               RegionConfig(name="right", min_mm=(200.0, -1.0, -1.0), max_mm=(601.0, 301.0, 100.0)))
    return InspectionSettings.from_section(InspectionConfig(**(
        {"best_fit": False, "tolerance_lower_mm": -0.5, "tolerance_upper_mm": 0.5, "regions": regions} | kw)))


def judged(box, c, U=0.25, context=None):
    """The top inspected and judged with a point U independent from point to point (about 22 points averaged
    within the 4 mm smoothing radius at 1.5 mm spacing: the areas' U about a fifth of it)."""
    result = inspect_cloud(top_with_bumps(), box, c.criteria)
    u = GivenUncertainty(U).evaluate(result.points_mm, result.cad_normals, c.criteria.decision_k, np.eye(4), "none",
                                     None, None)
    return judge(result, u, c.criteria, context)


def area_at(result, centre):
    return [a for a in result.areas if np.hypot(a.centroid_mm[0] - centre[0], a.centroid_mm[1] - centre[1]) < 10]


def test_iso_rule_proves_out_proves_in_and_leaves_the_band_between_indeterminate(box):
    r = judged(box, cfg())
    (out,) = area_at(r, BUMPS["out"][0])
    (between,) = area_at(r, BUMPS["between"][0])
    assert out.decision == "nonconforming" and between.decision == "indeterminate"
    assert not area_at(r, BUMPS["in"][0])  # within tolerance - U: conformance proven, no area
    assert out.uncertainty_mm == pytest.approx(0.25 / np.sqrt(22.0), rel=0.2) and "nonconformance proven" in out.reason
    assert r.verdict == "fail" and r.judgement.verdict == "fail"
    assert r.judgement.reasons[0].startswith(f"area #{out.id} (upper) extreme")
    regions = {g.name: g for g in r.judgement.regions}
    assert regions["left"].verdict == "fail" and regions["right"].verdict == "indeterminate"
    assert regions["left"].test_uncertainty_ratio == pytest.approx(2.0)  # 1 mm / (2 x 0.25 mm)
    assert r.judgement.rule.as_dict() == {"name": "iso14253-1", "k": 2.0}


def test_without_the_failing_bump_the_indeterminate_area_decides(box):
    c = cfg(regions=(RegionConfig(name="right", min_mm=(200.0, -1.0, -1.0), max_mm=(601.0, 301.0, 100.0)),))
    r = judged(box, c)
    cut = r.points_mm[:, 0] > 200.0
    u = GivenUncertainty(0.25).evaluate(r.points_mm[cut], r.cad_normals[cut], 2.0, np.eye(4), "none", None, None)
    part = inspect_cloud(r.points_mm[cut], box, c.criteria)
    verdict = judge(part, u, c.criteria)
    assert verdict.verdict == "indeterminate" and [a.decision for a in verdict.areas] == ["indeterminate"]
    assert "within U of a limit" in verdict.judgement.reasons[0]


def test_the_guard_bands_areas_reuse_the_inspections_tree_and_the_cloud_goes_with_the_result(box, monkeypatch):
    """One inspection builds the cloud's KD tree once for the areas at the band and at the verdict's guard band
    (the result's ``deviation_cloud``), and nothing else keeps the cloud once the judged result is dropped."""
    points = top_with_bumps()
    n, trees, tree = len(points), [], deviation_areas.cKDTree
    monkeypatch.setattr(deviation_areas, "cKDTree", lambda q, *a, **k: trees.append(len(q) == n) or tree(q, *a, **k))
    c = cfg()
    result = inspect_cloud(points, box, c.criteria)
    assert result.points_mm is points and sum(trees) == 1  # the band's areas
    u = GivenUncertainty(0.25).evaluate(points, result.cad_normals, c.criteria.decision_k, np.eye(4), "none", None,
                                        None)
    searched, find = [], verdict_module.find_deviation_areas
    monkeypatch.setattr(verdict_module, "find_deviation_areas",
                        lambda cloud, *a: searched.append(id(cloud)) or find(cloud, *a))
    judged = judge(result, u, c.criteria)
    assert searched == [id(result.deviation_cloud)] and sum(trees) == 1  # the guard band's areas: the same tree
    assert judged.areas
    freed = weakref.ref(points)
    del points, result, judged, u
    gc.collect()
    assert freed() is None


def test_simple_rule_decides_by_the_value_and_says_so(box):
    r = judged(box, cfg(decision_rule="simple"))
    assert r.verdict == "fail" and {a.decision for a in r.areas} == {"nonconforming"}
    assert len(r.areas) == 2  # out and between (0.54 is outside the band): both nonconforming by the value
    assert any("simple acceptance" in why for why in r.judgement.reasons)


def test_an_uncertainty_as_wide_as_the_band_proves_nothing_conforming(box):
    c = cfg(tolerance_lower_mm=-0.5, tolerance_upper_mm=0.5)
    r = judged(box, c, U=3.0)  # the areas' U about 0.6 mm
    assert r.verdict == "indeterminate"
    assert any("leaves no room" in why for why in r.judgement.reasons)
    assert all(g.test_uncertainty_ratio < 1.0 for g in r.judgement.regions)
    gross = judged(box, cfg(tolerance_lower_mm=-0.1, tolerance_upper_mm=0.1), U=0.15)  # 0.8 > 0.1 + 0.15
    assert gross.verdict == "fail"


def test_deviations_in_doubt_prove_neither_a_fail_nor_a_pass(box):
    """An unsettled context (the cloud's pose on the CAD ambiguous, docs/verdict.md): the proven nonconforming area
    stays as found, but the whole and every region are indeterminate, that reason first."""
    why = "the cloud's pose on the CAD is ambiguous: the pose turned 180 deg ... fits as well"
    r = judged(box, cfg(), context=VerdictContext(unsettled=(why,)))
    assert [a.decision for a in area_at(r, BUMPS["out"][0])] == ["nonconforming"]
    assert r.verdict == "indeterminate" and r.judgement.reasons[0] == why
    assert {g.verdict for g in r.judgement.regions} == {"indeterminate"}
    assert all(why in g.reason for g in r.judgement.regions)


def test_a_held_verdict_is_indeterminate_and_the_nominal_installation_is_named(box):
    c = cfg()
    part = inspect_cloud(top_with_bumps()[::2], box, c.criteria)
    keep = np.abs(part.deviations_mm) < 0.2  # the flat top only: conformance is proven
    flat = inspect_cloud(part.points_mm[keep], box, c.criteria)
    u = GivenUncertainty(0.05).evaluate(flat.points_mm, flat.cad_normals, 2.0, np.eye(4), "none", None, None)
    assert judge(flat, u, c.criteria).verdict == "pass"
    held = judge(flat, u, c.criteria, VerdictContext(holds=("the last verification is 30 h old, more than 24 h",)))
    assert held.verdict == "indeterminate" and "30 h old" in " ".join(held.judgement.reasons)
    nominal = judge(flat, u, c.criteria, VerdictContext(installation={"source": "nominal"}))
    assert any("nominal mounts" in why for why in nominal.judgement.reasons)


@pytest.mark.slow
def test_report_states_the_rule_the_budget_the_ratios_and_maps_the_uncertainty(box, tmp_path):
    import json

    from tandemscan.pipeline.inspection.inspection_job import Measurement, ReportOutput, run_inspection
    from tandemscan.pipeline.inspection.report import InspectedPart

    c = cfg(views=("top",), map_width_px=250)
    context = VerdictContext(installation={"source": "calibration", "file": "cal.json",
                                           "date": "2026-12-05T18:00:00+00:00"})
    out = run_inspection(Measurement(top_with_bumps(3.0), uncertainty=GivenUncertainty(0.25)), InspectedPart(box), c,
                         ReportOutput(tmp_path), context=context)
    data = json.loads((tmp_path / "report.json").read_text())["inspection"]
    assert data["verdict"] == out.result.verdict == "fail"
    assert data["decision_rule"] == {"name": "iso14253-1", "k": 2.0}
    assert data["uncertainty"]["median_mm"] == pytest.approx(0.25) and "cloud" in data["uncertainty"]["budget_mm"]
    assert {d["decision"] for d in data["deviations"]} == {"nonconforming", "indeterminate"}
    assert data["installation"]["file"] == "cal.json" and data["verdict_reasons"]
    assert [g["name"] for g in data["region_verdicts"]] == ["left", "right"]
    assert "uncertainty-map" in {f["name"] for f in data["figures"]}
    html = (tmp_path / "report.html").read_text()
    assert 'class="verdict fail"' in html and "ISO 14253-1 (k = 2)" in html and 'id="uncertainty"' in html
    assert 'id="region-verdicts"' in html and "2.0 : 1" in html and "installation: calibration, cal.json" in html
    ply = read_ply_vertices(tmp_path / "cloud_deviation.ply")
    assert np.allclose(ply["uncertainty_mm"], 0.25)
