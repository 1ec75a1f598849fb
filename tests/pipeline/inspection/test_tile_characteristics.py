"""A template's characteristics and the deviation areas' close-ups of a tiled cloud from the points of the whole cloud
in their regions (``region_points``, docs/compute.md "Tiles"): the untiled cloud's, and right over a small feature
that the report's even sample has hardly a point of.

The generated part of ``test_tile_areas`` (the wavy sheet of ``tests/pipeline/stitching/test_tiles.py`` in three
tiles), with a CAD whose triangles are in two face groups (x below and above 120 mm, F).
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from tandemscan.config.inspection_template import InspectionTemplate
from tandemscan.config.models import InspectionConfig
from tandemscan.pipeline.compute import LocalBackend
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.frames import transform_points
from tandemscan.pipeline.inspection import inspection_job
from tandemscan.pipeline.inspection.characteristics import sample_surface
from tandemscan.pipeline.inspection.inspect import CadSurface
from tandemscan.pipeline.inspection.inspection_job import (
    AlignmentStart,
    InspectionSettings,
    Measurement,
    ReportOutput,
    align_and_inspect,
)
from tandemscan.pipeline.inspection.point_uncertainty import GivenUncertainty
from tandemscan.pipeline.inspection.qif import RESULTS_FILE
from tandemscan.pipeline.inspection.region_points import Region, budgeted
from tandemscan.pipeline.inspection.report import InspectedPart
from tandemscan.pipeline.inspection.tile_inspection import TiledInspection

from tests.pipeline.inspection.test_tile_areas import _grid_F, _x_W, tiled_part, written_tiles
from tests.pipeline.stitching.test_tiles import T_F_W, cad_mesh

DIP_XY_MM = (210.0, 15.0)


def grouped_cad() -> CadSurface:
    """The sheet's CAD with its triangles in face group 1 (centroid x < 120 mm) and 2 (the others)."""
    mesh = cad_mesh()
    v, t = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    mesh.triangle_material_ids = o3d.utility.IntVector(
        np.where(v[t].mean(axis=1)[:, 0] < 120.0, 1, 2).astype(np.int32))
    return CadSurface(mesh)


def template(characteristics: list[dict]) -> InspectionTemplate:
    return InspectionTemplate.model_validate({
        "part": "generated wavy sheet", "part_number": "SHEET-1", "smoothing_mm": 3.0,
        "patches": {"middle": {"min_mm": [100.0, -30.0, -20.0], "max_mm": [140.0, 30.0, 20.0]},
                    "right": {"face_groups": [2]}},
        "characteristics": characteristics})


SHEET_TEMPLATE = [
    {"id": "SP-DIP", "name": "the dip's profile", "kind": "surface_profile",
     "region": {"min_mm": [190.0, -5.0, -20.0], "max_mm": [230.0, 35.0, 20.0]}},
    {"id": "SP-MID", "name": "the middle's profile", "kind": "surface_profile", "region": {"patch": "middle"},
     "lower_mm": -0.2, "upper_mm": 0.2},
    {"id": "SP-RIGHT", "name": "the right half (a face group)", "kind": "surface_profile",
     "region": {"patch": "right"}},
    {"id": "SP-BOTH", "name": "a box across both groups, on the first", "kind": "surface_profile",
     "region": {"min_mm": [100.0, -40.0, -20.0], "max_mm": [150.0, 40.0, 20.0], "face_groups": [1]}},
    {"id": "FL-1", "name": "a strip's flatness", "kind": "flatness",
     "region": {"min_mm": [40.0, -10.0, -20.0], "max_mm": [48.0, 10.0, 20.0]}, "upper_mm": 2.0},
    {"id": "SEC-1", "name": "across at x 120", "kind": "section", "point_mm": [120.0, 0.0, 0.0],
     "normal": [1.0, 0.0, 0.0], "half_width_mm": 1.0},
    {"id": "SEC-2", "name": "along at y 15, in the middle", "kind": "section", "point_mm": [0.0, 15.0, 0.0],
     "normal": [0.0, 1.0, 0.0], "region": {"patch": "middle"}},
]


def inspected(out: Path, points_W: np.ndarray, normals_W: np.ndarray, part: InspectedPart,
              whole: TiledInspection | None = None):
    settings = InspectionSettings.from_section(InspectionConfig(
        views=("isometric",), map_width_px=200, regions=(), reference_spheres=(), alignment="none",
        tolerance_lower_mm=-0.1, tolerance_upper_mm=0.1))
    return align_and_inspect(Measurement(points_W, normals_W, GivenUncertainty(0.02)), part, settings,
                             ReportOutput(out, json_name=None), AlignmentStart(T_F_W, "the sheet's anchor", T_F_W),
                             whole=whole)


def whole_and_tiled(tmp_path: Path, defects, characteristics: list[dict], every: int):
    """The part with ``defects`` inspected whole (untiled) and tiled beside its every ``every``-th point."""
    xy = _grid_F(np.random.default_rng(1))
    x_W = _x_W(xy)
    edges = [float(np.quantile(x_W, 1 / 3)), float(np.quantile(x_W, 2 / 3))]
    (tmp_path / "store").mkdir()
    cloud = tiled_part(tmp_path / "store", xy, defects, edges)
    part = InspectedPart(grouped_cad(), template(characteristics), {"serial": "S1"})
    normals = np.concatenate([np.load(Path(cloud.store) / t.file)["normals"] for t in cloud.tiles])
    untiled = inspected(tmp_path / "whole", cloud.points(), normals, part)
    sample = cloud.every_kth(every)
    tiled = inspected(tmp_path / "tiled", sample.points_mm, sample.normals, part,
                      TiledInspection(cloud.tiles, cloud.store, LocalBackend()))
    return untiled, tiled, sample


def qif_values(path: Path) -> list[tuple[str, str]]:
    """What results.qif measured: each characteristic's status and values, each profile's points and deviations."""
    tags = {"CharacteristicStatusEnum", "OtherCharacteristicStatus", "Value", "MaxValue", "MinValue", "Points",
            "Deviations"}
    return [(e.tag.split("}")[1], e.text or "") for e in ET.parse(path).iter() if e.tag.split("}")[1] in tags]


def test_the_tiled_characteristics_and_results_qif_are_the_untiled_clouds(tmp_path):
    """Every characteristic kind but the edge, boxes, a named patch, a face group, sections with and without a patch:
    from every third point the tiled inspection's characteristics equal the whole cloud's (each its own value,
    uncertainty, status, worst place and points), and so do results.qif's values."""
    dip = (*DIP_XY_MM, -0.3, 5.0)
    untiled, tiled, _ = whole_and_tiled(tmp_path, [(100.0, 0.0, 0.4, 6.0), dip], SHEET_TEMPLATE, 3)
    assert {c.status for c in untiled.characteristics} >= {"fail", "pass"}
    for a, b in zip(tiled.characteristics, untiled.characteristics, strict=True):
        assert (a.id, a.status, a.points, a.method) == (b.id, b.status, b.points, b.method)
        for name in ("actual_mm", "uncertainty_mm", "worst_plus_mm", "worst_minus_mm"):
            assert getattr(a, name) == pytest.approx(getattr(b, name), rel=1e-9, abs=1e-9), (a.id, name)
        np.testing.assert_allclose(a.at_mm, b.at_mm, rtol=0, atol=1e-9)
        np.testing.assert_allclose(a.deviations_mm, b.deviations_mm, rtol=0, atol=1e-9)
    assert qif_values(tmp_path / "tiled" / RESULTS_FILE) == qif_values(tmp_path / "whole" / RESULTS_FILE)
    assert [c["points"] for c in tiled.data["closeups"]] == [c["points"] for c in untiled.data["closeups"]]


def test_a_characteristic_over_a_dent_the_sample_hardly_sees_is_measured_from_every_point(tmp_path):
    """A dent 0.6 mm deep about 10 mm across, a profile over a 20 mm square about it: the report's sample (every 150th
    point, about 10 mm apart) holds a few points there, too few to measure it; the tiles' points there measure it
    as the whole cloud does (fail), and the dent's close-up draws every point around it."""
    spec = {"id": "SP-DENT", "name": "the dent's profile", "kind": "surface_profile",
            "region": {"min_mm": [DIP_XY_MM[0] - 10.0, DIP_XY_MM[1] - 10.0, -20.0],
                       "max_mm": [DIP_XY_MM[0] + 10.0, DIP_XY_MM[1] + 10.0, 20.0]}}
    untiled, tiled, sample = whole_and_tiled(tmp_path, [(*DIP_XY_MM, -0.6, 2.5)], [spec], 150)
    sample_F = transform_points(T_F_W, sample.points_mm)
    in_box = np.all(np.abs(sample_F[:, :2] - DIP_XY_MM) <= 10.0, axis=1)
    assert in_box.sum() < 20  # the sample alone: "not measured" (characteristics.MIN_POINTS)
    (a,), (b,) = tiled.characteristics, untiled.characteristics
    assert b.status == a.status == "fail" and a.points == b.points > 400
    assert a.actual_mm == pytest.approx(b.actual_mm, abs=1e-9) and a.actual_mm < -0.3
    (shown,) = tiled.data["closeups"]
    assert shown == untiled.data["closeups"][0]


BOX_TEMPLATE = {
    "part": "box", "part_number": "BOX-1",
    "alignment": {"method": "datums", "datums": [{"feature": "plane", "patch": "bottom"},
                                                 {"feature": "line", "patch": "front"},
                                                 {"feature": "point", "patch": "left"}]},
    "patches": {"bottom": {"min_mm": [5, 5, -2], "max_mm": [395, 195, 2]},
                "front": {"min_mm": [5, -2, 5], "max_mm": [395, 2, 95]},
                "left": {"min_mm": [-2, 85, 35], "max_mm": [2, 115, 65]},  # 90 points, 4 of the sample's
                "top": {"min_mm": [5, 5, 98], "max_mm": [395, 195, 102]}},
    "characteristics": [{"id": "SP-TOP", "name": "top", "kind": "surface_profile", "region": {"patch": "top"},
                         "lower_mm": -0.2, "upper_mm": 0.2}]}


def test_a_datum_frame_of_a_tiled_cloud_is_fitted_to_every_point_in_its_patches(tmp_path):
    """The box of ``test_characteristics``' datum test (its top raised 0.5 mm over its last 150 mm, the point datum's
    patch 30 x 30 mm), in three tiles: the sample (every 20th point) has too few points in that patch to fit it; the
    3-2-1 frame fitted to every point there puts the box back (to 0.05 mm: 90 points) as the whole cloud's does, within
    a micrometre of it (the best fit before it, from the sample, moves the patches' edges), and the top's profile reads
    the same."""
    box = o3d.geometry.TriangleMesh.create_box(400.0, 200.0, 100.0)
    cad = CadSurface(box)
    p = sample_surface(np.asarray(box.vertices), np.asarray(box.triangles), 0.1, seed=5)
    p = p + np.random.default_rng(5).normal(0.0, 0.02, p.shape)
    p[(p[:, 2] > 99.9) & (p[:, 0] > 250.0), 2] += 0.5
    T_W_F = F.from_rotvec([1.0, -2.0, 0.5], np.radians(0.3) * np.array([0.6, 0.8, 0.0]))
    p_W = F.transform_points(T_W_F, p)
    cloud = written_tiles(tmp_path, p_W, F.rotate_vectors(T_W_F, cad.closest(p).normals),
                          np.quantile(p_W[:, 0], [1 / 3, 2 / 3]).tolist())
    part = InspectedPart(cad, InspectionTemplate.model_validate(BOX_TEMPLATE))
    settings = InspectionSettings.from_section(InspectionConfig(
        views=("top",), map_width_px=150, best_fit=False, regions=(), reference_spheres=()), part.template)
    sample = cloud.every_kth(20)
    untiled, tiled = (align_and_inspect(Measurement(m.points_mm, m.normals), part, settings,
                                        ReportOutput(tmp_path / name, json_name=None), whole=whole)
                      for m, name, whole in ((cloud.every_kth(1), "whole", None), (sample, "tiled", TiledInspection(
                          cloud.tiles, cloud.store, LocalBackend()))))
    assert untiled.data["alignment"]["method"] == tiled.data["alignment"]["method"] == "datums"
    corners = np.asarray(box.vertices)
    placed = [F.transform_points(np.asarray(out.data["alignment"]["T_F_W"]) @ T_W_F, corners)
              for out in (tiled, untiled)]
    assert np.abs(placed[0] - corners).max() < 0.05 and np.abs(placed[0] - placed[1]).max() < 1e-3
    (a,), (b,) = tiled.characteristics, untiled.characteristics
    assert a.status == b.status == "fail" and abs(a.points - b.points) <= 2
    assert a.actual_mm == pytest.approx(b.actual_mm, abs=1e-3)


def test_a_region_over_the_budget_is_thinned_and_its_characteristic_says_so(tmp_path, monkeypatch):
    """The budget of the regions' points at 3,000: a profile over the whole sheet (30,000 points) is evaluated on one in
    every k of them and says so; the dip's close-up takes its share of the rest."""
    monkeypatch.setattr(inspection_job, "REGION_POINTS", 3_000)
    xy = _grid_F(np.random.default_rng(1))
    x_W = _x_W(xy)
    cloud = tiled_part(tmp_path, xy, [(*DIP_XY_MM, -0.3, 5.0)], np.quantile(x_W, [1 / 3, 2 / 3]).tolist())
    part = InspectedPart(grouped_cad(), template([{"id": "SP-ALL", "name": "all", "kind": "surface_profile",
                                                   "region": {"min_mm": [-100, -100, -20], "max_mm": [400, 100, 20]}}]))
    sample = cloud.every_kth(3)
    out = inspected(tmp_path / "out", sample.points_mm, sample.normals, part,
                    TiledInspection(cloud.tiles, cloud.store, LocalBackend()))
    (c,) = out.characteristics
    (shown,) = out.data["closeups"]
    step = int(re.search(r"on one in every (\d+) points of its region", c.method)[1])
    assert 0 <= c.points * step - len(cloud) < 3 * step  # every step-th of each of the three tiles' points
    assert 2_000 < c.points + shown["points"] < 3_300 and c.status == "fail"


def test_a_region_over_its_share_of_the_budget_is_thinned_and_the_small_ones_are_not():
    """Counted on an even sample: the small region whole, the large one thinned to what the budget leaves."""
    rng = np.random.default_rng(0)
    p = np.c_[rng.uniform(0, 1000, 50_000), rng.uniform(0, 100, 50_000), np.zeros(50_000)]
    small, large = Region.box((0, 0, -1), (10, 100, 1)), Region.box((0, 0, -1), (1000, 100, 1))
    a, b = budgeted([small, large], p, None, 10.0, budget=100_000)  # about 5,000 and 500,000 points
    assert a.step == 1 and b.step == pytest.approx(500_000 / 95_000, abs=1)
    assert budgeted([small], p, None, 10.0, budget=100_000)[0].step == 1
