"""Coverage as a figure (docs/planning.md, "Coverage"): the floor leaves no room only where it really does (a
part on supports is scanned from below where the arm fits), the measured share of the surface where a pose fits,
and the default part's inspection regions for the default part only."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from tandemscan.config import load_config
from tandemscan.config.models import DEFAULT_PART_REGIONS, RegionConfig
from tandemscan.pipeline.planning.coverage import REASON_NO_POSE, CoverageFigures, triangle_geometry
from tandemscan.pipeline.planning.parameters import PartPlanning
from tandemscan.pipeline.planning.plan import Plan, Scan
from tandemscan.pipeline.planning.planner import plan_part


def blade(bottom_mm: float) -> o3d.geometry.TriangleMesh:
    """A blade-like slab along x: 2.5 m long, an elliptic section 600 mm wide and 120 mm thick, its lowest point
    ``bottom_mm`` above the floor."""
    mesh = o3d.geometry.TriangleMesh.create_cylinder(radius=1.0, height=2500.0, resolution=48, split=20)
    mesh.rotate(mesh.get_rotation_matrix_from_xyz((0.0, np.pi / 2, 0.0)), center=(0.0, 0.0, 0.0))
    v = np.asarray(mesh.vertices) * [1.0, 300.0, 60.0] + [0.0, 0.0, bottom_mm + 60.0]
    mesh.vertices = o3d.utility.Vector3dVector(v)
    return mesh.compute_vertex_normals()


def box(bottom_mm: float) -> o3d.geometry.TriangleMesh:
    """A 1 m cube, its bottom face ``bottom_mm`` above the floor."""
    return o3d.geometry.TriangleMesh.create_box(1000.0, 1000.0, 1000.0).translate((0.0, 0.0, bottom_mm))


def test_a_blade_on_supports_is_scanned_from_below_where_the_arm_fits():
    config = load_config()
    start = config.sim.tracking_start
    tracker = (start.x_mm, start.y_mm, np.radians(start.heading_deg))
    area, normal, _ = triangle_geometry(blade(0.0))
    underside = float(area[normal[:, 2] < -0.5].sum())
    on_floor = plan_part(blade(0.0), PartPlanning.from_config(config), tracker_start=tracker).coverage
    raised = plan_part(blade(1000.0), PartPlanning.from_config(config), tracker_start=tracker)
    # resting on the floor, its underside has no room for a scanner pose
    assert on_floor.floor_contact_mm2 == pytest.approx(underside, rel=0.05)
    booked = sum(lo.area_mm2 for lo in on_floor.left_out if lo.reason == REASON_NO_POSE)
    assert booked == pytest.approx(on_floor.floor_contact_mm2)
    # 1 m up, nothing is booked as facing the floor: the underside is planned, scanned looking up from below
    assert raised.coverage.floor_contact_mm2 == 0.0
    assert all(lo.reason != REASON_NO_POSE for lo in raised.coverage.left_out)
    up = [p for p in raised.poses if p.T_F_S[2, 2] > np.cos(np.radians(50.0))]
    assert up and all(p.T_F_S[2, 3] < 1000.0 for p in up)
    assert raised.coverage.coverage_pct > 90.0
    assert raised.coverage.seen_area_mm2 > on_floor.seen_area_mm2 + 0.8 * underside


@pytest.mark.parametrize("bottom_mm, fits_m2", [(0.0, 5.0), (1000.0, 6.0)])
def test_the_measured_share_counts_the_surface_where_a_pose_fits(bottom_mm, fits_m2):
    """A 1 m cube with its top face measured: on the floor a pose fits on 5 of its faces (20 % measured); on
    supports 1 m up on all 6 (16.7 %)."""
    config = load_config()
    mesh = box(bottom_mm)
    _, normal, _ = triangle_geometry(mesh)
    plan = Plan(name="cube", steps=[Scan()], coverage_pct=80.0)
    figures = CoverageFigures.of_plan(plan, mesh, config.scanner.sweet_spot_mm,
                                      np.radians(config.planning.incidence_limit_deg))
    assert figures.pose_fits.sum() == 2 * fits_m2  # two triangles a face
    measured = figures.with_measured(mesh, normal[:, 2] > 0.99)
    assert measured.measured_pct == pytest.approx(100.0 / fits_m2, abs=0.01)
    assert measured.as_dict() == {"planned_pct": 80.0, "measured_pct": measured.measured_pct,
                                  "of": "surface where a pose fits", "left_out": []}
    assert figures.with_measured(mesh, np.ones(3, bool)) == figures  # another mesh: the share stays unknown


def test_the_default_parts_regions_apply_to_the_default_part_only(tmp_path):
    config = load_config()
    assert config.part_inspection().regions == DEFAULT_PART_REGIONS  # the parametric nose
    mesh_part = config.model_copy(update={"part": config.part.model_copy(update={"mesh": tmp_path / "p.stl"})})
    assert mesh_part.part_inspection().regions == ()  # a part mesh without configured regions: none
    wing = (RegionConfig(name="wing", min_mm=(0.0, 0.0, 0.0), max_mm=(1.0, 1.0, 1.0)),)
    configured = mesh_part.model_copy(update={"inspection": config.inspection.model_copy(update={"regions": wing})})
    assert configured.part_inspection().regions == wing
    (tmp_path / "cell.toml").write_text("[inspection]\nregions = []\n")
    assert load_config(tmp_path / "cell.toml").part_inspection().regions == ()  # configured as none
