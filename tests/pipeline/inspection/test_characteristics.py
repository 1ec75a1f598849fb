"""Inspection templates and characteristics: the shipped templates load, bad ones are refused by key, and on
clouds sampled from the simulator's as-built parts each seeded deviation shows up in the characteristic that
covers it with the expected status; a 0.5 mm edge offset of the hatch is measured within 0.1 mm."""

from __future__ import annotations

import functools

import numpy as np
import pytest
from tandemscan.config import ConfigError, load_config
from tandemscan.config.inspection_template import find_template, load_template, shipped_template
from tandemscan.config.models import InspectionConfig
from tandemscan.pipeline.geometry.part import load_part_mesh
from tandemscan.pipeline.inspection.characteristics import MeasuredCloud, evaluate, sample_surface
from tandemscan.pipeline.inspection.decision import DecisionRule
from tandemscan.pipeline.inspection.inspect import CadSurface, InspectionError
from tandemscan.pipeline.inspection.region_points import characteristic_region
from tandemscan.sim_drivers.as_built import scanned_part_mesh

U_MM = 0.02  # per-point expanded uncertainty given to the characteristics here
NOISE_MM = 0.05


@functools.cache
def as_built_part(config_file: str) -> tuple[CadSurface, np.ndarray, np.ndarray]:
    """The CAD surface of ``config_file``'s part and the vertices (mm) and triangles of the part as built, made once
    per configuration (about 2 s each) and shared by the clouds sampled from it; read only."""
    config = load_config(config_file)
    built = scanned_part_mesh(config)
    return CadSurface(load_part_mesh(config.part)), np.asarray(built.vertices), np.asarray(built.triangles)


def sampled_cloud(config_file: str, box_min, box_max, per_mm2: float, seed: int) -> MeasuredCloud:
    """The simulated part as built (``config_file``), sampled on its triangles inside the box with the
    scanner's noise along the CAD normal, against the CAD: what a measured cloud placed in F looks like."""
    cad, V, T = as_built_part(config_file)
    c = V[T].mean(axis=1)
    keep = np.all((c >= box_min) & (c <= box_max), axis=1)
    p = sample_surface(V, T[keep], per_mm2, seed=seed)
    rng = np.random.default_rng(seed)
    p = p + rng.normal(0.0, NOISE_MM, len(p))[:, None] * cad.closest(p).normals
    cp = cad.closest(p)
    return MeasuredCloud(p, cp.signed_mm, cp.triangle_ids, np.full(len(p), U_MM), cad)


def template_of(config_file: str, name: str = "default-part.toml"):
    """The shipped template ``name`` under the general tolerance of ``config_file``'s ``[inspection]``, as a job
    with that configuration evaluates it."""
    band = load_config(config_file).inspection
    return load_template(shipped_template(name)).with_general_tolerance(band.tolerance_lower_mm,
                                                                       band.tolerance_upper_mm)


@pytest.fixture(scope="module")
def as_built_results():
    cloud = sampled_cloud("config/as-built-example.toml", (-1450.0, 0.0, 540.0), (1200.0, 1100.0, 980.0), 0.4, 3)
    return {r.id: r for r in evaluate(template_of("config/as-built-example.toml"), cloud, DecisionRule())}


def test_shipped_templates_load_and_the_default_part_finds_its_own(tmp_path):
    default = load_template(shipped_template())
    assert default.part_number == "TS-NOSE-3000" and len(default.characteristics) >= 5
    assert {c.kind for c in default.characteristics} >= {"surface_profile", "flatness", "section"}
    for name in ("hatch-part.toml", "barrel-panel.toml"):
        assert load_template(shipped_template(name)).characteristics
    hatch = load_config("config/hatch-example.toml")
    found = find_template(hatch.part.mesh, configured=hatch.inspection.template)
    assert found.resolve() == shipped_template("hatch-part.toml").resolve()
    assert find_template(None) == shipped_template()
    mesh = tmp_path / "panel.ply"
    assert find_template(mesh) is None
    (tmp_path / "panel.inspection.toml").write_text("")
    assert find_template(mesh) == tmp_path / "panel.inspection.toml"


@pytest.mark.parametrize("body, needle", [
    ("[[characteristics]]\nid='A'\nname='a'\nkind='flatness'\nregion={patch='nope'}\nupper_mm=0.1\n",
     "patches ['nope'] are not defined"),
    ("[[characteristics]]\nid='A'\nname='a'\nkind='surface_profile'\nregion={min_mm=[0,0,0],max_mm=[1,1,1]}\n"
     "lower_mm=0.1\nupper_mm=-0.1\n", "must be below upper_mm"),
    ("[[characteristics]]\nid='A'\nname='a'\nkind='cylindricity'\nupper_mm=0.1\n", "characteristics.0"),
    ("[[characteristics]]\nid='A'\nname='a'\nkind='surface_profile'\nregion={min_mm=[0,0,0],max_mm=[1,1,1]}\n"
     "lower_mm=-0.1\n", "give both lower_mm and upper_mm, or neither"),
    ("[[characteristics]]\nid='A'\nname='a'\nkind='flatness'\nregion={min_mm=[0,0,0],max_mm=[1,1,1]}\n",
     "upper_mm"),
    ("[[characteristics]]\nid='A'\nname='a'\nkind='section'\npoint_mm=[0,0,0]\nnormal=[1,0,0]\nlower_mm=-1\n"
     "upper_mm=1\n[[characteristics]]\nid='A'\nname='b'\nkind='section'\npoint_mm=[0,0,0]\nnormal=[0,1,0]\n"
     "lower_mm=-1\nupper_mm=1\n", "ids used twice"),
])
def test_bad_templates_are_refused_naming_the_key(tmp_path, body, needle):
    path = tmp_path / "t.toml"
    path.write_text("part = 'p'\npart_number = 'P-1'\n" + body)
    with pytest.raises(ConfigError, match="t.toml") as e:
        load_template(path)
    assert needle in str(e.value)


def test_profiles_and_sections_take_the_general_tolerance_and_the_others_keep_their_own():
    """A drawing's general surface profile tolerance (ISO 22081, ``[inspection] tolerance_*``) is the limit of each
    profile and section of the default part; its flatness keeps its own 0.5 mm; a template not given the general
    tolerance is refused rather than evaluated without limits."""
    template = load_template(shipped_template())
    assert set(template.needs_general_tolerance) == {"SP-1", "SP-2", "SP-3", "SEC-1", "SEC-2"}
    resolved = {c.id: c for c in template.with_general_tolerance(-0.4, 0.6).characteristics}
    assert all((resolved[i].lower_mm, resolved[i].upper_mm) == (-0.4, 0.6) for i in template.needs_general_tolerance)
    assert (resolved["FL-1"].lower_mm, resolved["FL-1"].upper_mm) == (0.0, 0.5)
    assert not template.with_general_tolerance(-0.4, 0.6).needs_general_tolerance
    cloud = sampled_cloud("config/sim-cell.toml", (-400.0, 900.0, 600.0), (-300.0, 1100.0, 700.0), 0.2, 1)
    with pytest.raises(InspectionError, match="SP-1, SP-2, SP-3, SEC-1, SEC-2 of TS-NOSE-3000 take the general"):
        evaluate(template, cloud, DecisionRule())


def test_template_alignment_becomes_the_inspection_config(tmp_path):
    path = tmp_path / "t.toml"
    path.write_text("part='p'\npart_number='P'\n[alignment]\nmethod='best-fit'\ndatum_patches=['d']\n"
                    "[patches.d]\nmin_mm=[0,0,0]\nmax_mm=[1,1,1]\n[[characteristics]]\nid='F'\nname='f'\n"
                    "kind='flatness'\nregion={patch='d'}\nupper_mm=0.1\n")
    cfg = load_template(path).inspection_config(InspectionConfig())
    assert cfg.alignment == "best-fit" and cfg.datum_regions == ("datum:d",)
    assert cfg.regions[-1].min_mm == (0.0, 0.0, 0.0)


@pytest.mark.slow
def test_each_seeded_deviation_shows_in_its_characteristic(as_built_results):
    r = as_built_results
    # the rear end bent 0.3 mm (+y): body profile and flatness; the 0.3 mm dent at x -350: rear nose and
    # its section; the 0.45 mm bulge and 0.25 mm dent: front nose; the section at x 400 crosses none. The
    # worst of the averaged deviations reads high by the largest of the averaged noise (a few hundredths).
    # Under the as-built example's general tolerance of +-0.3 mm (U 0.02 mm): the bulge fails its profile, the
    # 0.3 mm dent and bend, at the limit, prove no conformance, the 0.3 mm bend is within the 0.5 mm flatness
    assert {c.lower_mm for c in r.values() if c.kind != "flatness"} == {-0.3} and r["FL-1"].upper_mm == 0.5
    assert r["SP-1"].status != "pass" and r["SP-1"].actual_mm == pytest.approx(0.3, abs=0.07)
    assert r["FL-1"].status == "pass" and r["FL-1"].actual_mm == pytest.approx(0.3, abs=0.07)
    assert r["SP-2"].status != "pass" and r["SP-2"].actual_mm == pytest.approx(-0.3, abs=0.07)
    assert np.linalg.norm(np.subtract(r["SP-2"].at_mm, (-350.0, 996.2, 680.0))) < 15.0
    assert r["SP-3"].status == "fail" and r["SP-3"].worst_plus_mm == pytest.approx(0.45, abs=0.07)
    assert r["SP-3"].worst_minus_mm == pytest.approx(-0.25, abs=0.07)
    assert r["SEC-1"].status != "pass" and r["SEC-1"].actual_mm == pytest.approx(-0.3, abs=0.07)
    assert r["SEC-2"].status == "pass" and abs(r["SEC-2"].actual_mm) < 0.07
    assert all(c.uncertainty_mm == U_MM for c in r.values() if c.kind != "flatness")
    curve = r["SEC-1"].curve
    assert np.all(np.diff(curve.arc_mm) >= 0) and curve.deviation_mm.min() == pytest.approx(-0.3, abs=0.07)


@pytest.mark.slow
def test_a_surface_profile_near_a_limit_within_u_is_indeterminate(as_built_results):
    sp2 = as_built_results["SP-2"]
    template = load_template(shipped_template())
    spec = next(c for c in template.characteristics if c.id == "SP-2")
    cloud = sampled_cloud("config/as-built-example.toml", (-420.0, 900.0, 620.0), (-280.0, 1100.0, 740.0), 0.4, 5)
    near = spec.model_copy(update={"lower_mm": sp2.actual_mm - 0.01, "upper_mm": 0.3})
    wide = MeasuredCloud(cloud.points_mm, cloud.deviations_mm, cloud.triangle_ids, np.full(len(cloud.points_mm), 0.05),
                         cloud.surface)
    out = evaluate(template.model_copy(update={"characteristics": (near,)}), wide, DecisionRule())[0]
    assert out.status == "indeterminate" and out.uncertainty_mm == 0.05


@pytest.mark.slow
def test_the_hatch_edge_offset_is_measured_within_a_tenth(tmp_path):
    """The hatch's +x edge 0.5 mm out as built (the opening larger): -0.5 mm within 0.1 mm, fail; the other
    edges on CAD: pass."""
    cloud = sampled_cloud("config/hatch-example.toml", (-1200.0, 900.0, 560.0), (-700.0, 1100.0, 960.0), 1.0, 4)
    template = template_of("config/hatch-example.toml", "hatch-part.toml")
    r = {c.id: c for c in evaluate(template, cloud, DecisionRule())}
    assert r["EDGE-1"].actual_mm == pytest.approx(-0.5, abs=0.1) and r["EDGE-1"].status == "fail"
    for other in ("EDGE-2", "EDGE-3", "EDGE-4"):
        assert abs(r[other].actual_mm) < 0.1 and r[other].status == "pass"
    assert r["EDGE-1"].points > 100
    # a tiled cloud gathers each edge's points by its region (region_points.characteristic_region): the edge measured
    # on those alone is the edge measured on the whole cloud (the other kinds: test_tile_characteristics.py)
    for spec in (c for c in template.characteristics if c.kind == "edge"):
        inside = characteristic_region(spec, template, cloud.surface).mask(cloud.points_mm, cloud.triangle_ids)
        assert 0 < inside.mean() < 0.2
        (alone,) = evaluate(template.model_copy(update={"characteristics": (spec,)}), MeasuredCloud(
            cloud.points_mm[inside], cloud.deviations_mm[inside], cloud.triangle_ids[inside],
            cloud.uncertainty_mm[inside], cloud.surface), DecisionRule())
        assert (alone.actual_mm, alone.points, alone.status) == (r[spec.id].actual_mm, r[spec.id].points,
                                                                 r[spec.id].status), spec.id


@pytest.mark.slow
def test_report_leads_with_the_characteristics_and_shows_each_area_close_up(tmp_path):
    """report.html: the characteristics table before the verdict and the maps; each deviation area has a
    close-up figure centred on it that draws its points, many of them beyond the band (blue: a dent)."""
    import json

    from matplotlib.image import imread
    from tandemscan.pipeline.inspection.inspection_job import (
        InspectionSettings,
        Measurement,
        ReportOutput,
        run_inspection,
    )
    from tandemscan.pipeline.inspection.report import InspectedPart

    cloud = sampled_cloud("config/as-built-example.toml", (-430.0, 900.0, 600.0), (-270.0, 1100.0, 760.0), 1.0, 6)
    cfg = InspectionConfig(views=("right",), map_width_px=300, best_fit=False, regions=())
    part = InspectedPart(cloud.surface, load_template(shipped_template()),
                         {"part_number": "TS-NOSE-3000", "serial": "SN-0001"})
    out = run_inspection(Measurement(cloud.points_mm), part, InspectionSettings.from_section(cfg),
                         ReportOutput(tmp_path))
    html = (tmp_path / "report.html").read_text()
    assert html.index('id="characteristics"') < html.index('id="verdict"') < html.index('id="map-0"')
    assert "SN-0001" in html and "<td class=\"l\">SP-2</td>" in html
    data = json.loads((tmp_path / "report.json").read_text())["inspection"]
    statuses = {c["id"]: c["status"] for c in data["characteristics"]}
    assert statuses["SP-2"] == "fail" and statuses["SEC-1"] == "fail" and statuses["SP-3"] == "not measured"
    # the profiles and sections under the job's general tolerance, the flatness under its own
    assert {(c["lower_mm"], c["upper_mm"]) for c in data["characteristics"] if c["kind"] != "flatness"} == {
        (cfg.tolerance_lower_mm, cfg.tolerance_upper_mm)}
    assert (tmp_path / "figures" / "section-SEC-1.png").is_file()
    areas = out.result.areas
    assert areas and len(data["closeups"]) == len(areas)
    for area, shown in zip(areas, data["closeups"], strict=True):
        assert shown["area"] == area.id and shown["centre_mm"] == pytest.approx(area.centroid_mm)
        assert shown["points"] > area.points and shown["beyond_band"] > 0.3 * area.points
        rgb = imread(tmp_path / shown["figure"])[..., :3]
        blue = (rgb[..., 2] > 0.6) & (rgb[..., 0] < 0.3) & (rgb[..., 1] < 0.5)
        assert blue.sum() > 200  # the dent's points drawn in the lower colours


@pytest.mark.slow
def test_the_barrel_panel_template_measures_every_characteristic_of_a_panel_on_its_cad():
    from tandemscan.pipeline.geometry.part import barrel_panel_mesh

    cad = CadSurface(barrel_panel_mesh())
    V, T = np.asarray(cad.mesh.vertices), np.asarray(cad.mesh.triangles)
    c = V[T].mean(axis=1)
    skin = np.asarray(cad.mesh.triangle_normals)[:, 2] > -0.5
    bands = skin & ((np.abs(c[:, 0]) < 80.0) | (np.abs(c[:, 0] - 1500.0) < 80.0))  # the sections and a crown
    p = sample_surface(V, T[bands], 0.5, seed=2)
    p = p[(np.abs(p[:, 0]) < 60.0) | (np.abs(p[:, 0] - 1500.0) < 60.0)]
    end = sample_surface(V, T[skin & (c[:, 0] > 1999.0) & (np.abs(c[:, 1]) < 2200.0)], 0.3, seed=3)
    p = np.vstack([p, end[(np.abs(end[:, 1]) < 600.0) & (np.abs(end[:, 2] - 600.0) < 300.0)]])
    rng = np.random.default_rng(2)
    p = p + rng.normal(0.0, NOISE_MM, len(p))[:, None] * cad.closest(p).normals
    cp = cad.closest(p)
    cloud = MeasuredCloud(p, cp.signed_mm, cp.triangle_ids, np.full(len(p), U_MM), cad)
    results = evaluate(template_of("config/large-cell.example.toml", "barrel-panel.toml"), cloud, DecisionRule())
    assert [r.status for r in results] == ["pass"] * len(results), [(r.id, r.status, r.actual_mm) for r in results]
    assert {r.kind for r in results} == {"surface_profile", "flatness", "section"}


@pytest.mark.slow
def test_a_datum_reference_frame_leaves_a_raised_end_where_a_best_fit_would_spread_it(tmp_path):
    """A 400 x 200 x 100 mm box whose top is raised 0.5 mm over its last 150 mm, given 0.3 deg and 2.3 mm off:
    the 3-2-1 frame of its bottom (plane), front (line) and left (point) faces puts it back to 0.01 mm, and
    the top's profile reads the whole 0.5 mm."""
    import open3d as o3d
    from tandemscan.pipeline.geometry import frames as F
    from tandemscan.pipeline.inspection.inspection_job import (
        InspectionSettings,
        Measurement,
        ReportOutput,
        align_and_inspect,
    )
    from tandemscan.pipeline.inspection.report import InspectedPart

    box = o3d.geometry.TriangleMesh.create_box(400.0, 200.0, 100.0)
    box.compute_triangle_normals()
    cad = CadSurface(box)
    p = sample_surface(np.asarray(box.vertices), np.asarray(box.triangles), 0.5, seed=5)
    rng = np.random.default_rng(5)
    p = p + rng.normal(0.0, 0.02, p.shape)
    p[(p[:, 2] > 99.9) & (p[:, 0] > 250.0), 2] += 0.5
    T_true = F.from_rotvec([1.0, -2.0, 0.5], np.radians(0.3) * np.array([0.6, 0.8, 0.0]))
    path = tmp_path / "t.toml"
    path.write_text("""part = 'box'\npart_number = 'BOX-1'\n[alignment]\nmethod = 'datums'
datums = [{feature = 'plane', patch = 'bottom'}, {feature = 'line', patch = 'front'},
          {feature = 'point', patch = 'left'}]
[patches.bottom]\nmin_mm = [5, 5, -2]\nmax_mm = [395, 195, 2]
[patches.front]\nmin_mm = [5, -2, 5]\nmax_mm = [395, 2, 95]
[patches.left]\nmin_mm = [-2, 5, 5]\nmax_mm = [2, 195, 95]
[patches.top]\nmin_mm = [5, 5, 98]\nmax_mm = [395, 195, 102]
[[characteristics]]\nid = 'SP-TOP'\nname = 'top'\nkind = 'surface_profile'\nregion = {patch = 'top'}
lower_mm = -0.2\nupper_mm = 0.2\n""")
    cfg = InspectionConfig(views=("top",), map_width_px=150, best_fit=False, regions=(), reference_spheres=())
    template = load_template(path)
    out = align_and_inspect(Measurement(F.transform_points(T_true, p)), InspectedPart(cad, template),
                            InspectionSettings.from_section(cfg, template), ReportOutput(tmp_path))
    T = out.data["alignment"]
    assert T["method"] == "datums"
    corners = np.asarray(box.vertices)
    moved = F.transform_points(np.asarray(T["T_F_W"]) @ T_true, corners) - corners
    assert np.abs(moved).max() < 0.01
    top = out.characteristics[0]
    assert top.actual_mm == pytest.approx(0.5, abs=0.03) and top.status == "fail"


def test_a_datum_frame_needs_a_plane_a_line_and_a_point_in_boxes(tmp_path):
    path = tmp_path / "t.toml"
    head = "part = 'p'\npart_number = 'P'\n[patches.a]\nmin_mm = [0, 0, 0]\nmax_mm = [1, 1, 1]\n"
    tail = "[[characteristics]]\nid = 'F'\nname = 'f'\nkind = 'flatness'\nregion = {patch = 'a'}\nupper_mm = 0.1\n"
    path.write_text(head + "[alignment]\nmethod = 'datums'\ndatums = [{feature = 'plane', patch = 'a'}]\n" + tail)
    with pytest.raises(ConfigError, match="a plane, a line and a point"):
        load_template(path)


@pytest.mark.slow
def test_the_simulated_scanner_sees_the_hatch_edge_offset_within_a_tenth():
    """Twelve views of the simulated scanner (its noise, its ray casting: walls seen at an angle) at the
    hatch of config/hatch-example.toml, the +x edge 0.5 mm out as built: -0.5 mm within 0.1 mm, fail; the
    other edges pass."""
    from tandemscan.sim_drivers.scan_views import views_over
    from tandemscan.sim_drivers.world import SimWorld

    config = load_config("config/hatch-example.toml")
    world = SimWorld(config)
    cad = CadSurface(load_part_mesh(config.part))
    centres = [(x, 1000.0, z) for x in (-1080.0, -950.0, -820.0) for z in (690.0, 830.0)]
    p = views_over(world, centres, (0.0, 1.0, 0.0), (1.0, 0.0, 0.0), (-15.0, 15.0), np.random.default_rng(1))
    cp = cad.closest(p)
    cloud = MeasuredCloud(p, cp.signed_mm, cp.triangle_ids, np.full(len(p), U_MM), cad)
    r = {c.id: c for c in evaluate(template_of("config/hatch-example.toml", "hatch-part.toml"), cloud,
                                   DecisionRule())}
    assert r["EDGE-1"].actual_mm == pytest.approx(-0.5, abs=0.1) and r["EDGE-1"].status == "fail"
    assert all(abs(r[e].actual_mm) < 0.1 and r[e].status == "pass" for e in ("EDGE-2", "EDGE-3", "EDGE-4"))
