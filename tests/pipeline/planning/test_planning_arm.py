"""Arm rasters (Eq. 15) on a box and a cylinder, the scanner pose geometry, reach and the closed-form IK."""

from __future__ import annotations

import math

import numpy as np
import open3d as o3d
import pytest
from tandemscan.config.models import ArmConfig, CellConfig
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.kinematics import ArmKinematics
from tandemscan.pipeline.geometry.raycast import make_scene
from tandemscan.pipeline.planning.arm import (
    ArmSetup,
    _snake,
    _travel,
    column_count,
    plan_station,
    raster_cells,
    row_count,
)
from tandemscan.pipeline.planning.ik import AnalyticIK
from tandemscan.pipeline.planning.parameters import PartPlanning
from tandemscan.pipeline.planning.stations import AgvStation

CELL = PartPlanning.from_config(CellConfig())
FOOTPRINT = CELL.footprint


def setup(ik) -> ArmSetup:
    return ArmSetup(ik, ArmConfig(), CELL.T_V2_B, CELL.T_E_S, FOOTPRINT, CELL.spacing, CELL.margin)


def box(lx: float, ly: float, lz: float) -> o3d.geometry.TriangleMesh:
    m = o3d.geometry.TriangleMesh.create_box(lx, ly, lz)
    m.translate([-lx / 2, -ly / 2, 0.0])
    return m


def station_below(y_mm: float) -> AgvStation:
    """A station on the -y side of the part driving along +x: the part on its left."""
    return AgvStation(0, 0.0, y_mm, 0.0, 0.0)


def test_eq15_counts_by_hand():
    # m = 0.8 * 360 = 288, n = 0.8 * 280 = 224
    assert column_count(848.2, 288.0) == 4  # ceil(2.95) + 1
    assert column_count(576.0, 288.0) == 3  # exactly p/m + 1 when it divides
    assert row_count(1500.0, 224.0) == 7
    assert row_count(224.0, 224.0) == 1


def test_box_raster_cells_by_hand():
    scene = make_scene(box(2000.0, 1000.0, 1000.0))
    st = station_below(-1300.0)
    cells, rows, cols = raster_cells(scene, st, 848.2, (0.0, 1000.0), 6000.0, FOOTPRINT)
    # profile on the near side: 1000 mm wall + 500 mm of roof to the middle -> 7 rows; 4 columns
    assert (rows, cols) == (7, 4)
    assert len(cells) == 28
    xs = sorted({round(float(c.point_F[0])) for c in cells})
    assert xs == pytest.approx([-424.1, -141.4, 141.4, 424.1], abs=1.0)
    wall = [c for c in cells if c.normal_F[1] < -0.9]
    roof = [c for c in cells if c.normal_F[2] > 0.9]
    assert len(wall) + len(roof) == 28
    assert all(abs(c.point_F[1] + 500.0) < 1e-3 for c in wall)
    assert all(abs(c.point_F[2] - 1000.0) < 1e-3 and -500.0 <= c.point_F[1] <= 0.0 for c in roof)
    # rows sit every h / i = 1500 / 7 mm along the profile: the first at 107 mm up the wall
    first = min(wall, key=lambda c: c.point_F[2])
    assert first.point_F[2] == pytest.approx(1500.0 / 14, abs=15.0)


def test_cylinder_raster_cells_lie_on_the_surface():
    cyl = o3d.geometry.TriangleMesh.create_cylinder(radius=500.0, height=1000.0, resolution=256)
    cyl.translate([0.0, 0.0, 500.0])
    scene = make_scene(cyl)
    st = station_below(-1300.0)
    step = 2 * math.pi * 1300.0 / 10  # the ten stations of the cylinder's station test
    cells, rows, cols = raster_cells(scene, st, step, (0.0, 1000.0), 6000.0, FOOTPRINT)
    assert cols == column_count(step, 288.0) == 4
    assert rows == 7  # centre columns: 1000 mm wall + about 500 mm roof
    for c in cells:
        r = math.hypot(c.point_F[0], c.point_F[1])
        on_wall = abs(r - 500.0) < 2.0 and abs(c.normal_F[2]) < 0.25  # normals are smoothed over n/4
        on_roof = abs(c.point_F[2] - 1000.0) < 1e-3 and c.normal_F[2] > 0.99
        assert on_wall or on_roof
        if on_wall:
            radial = np.r_[c.point_F[:2] / r, 0.0]
            assert radial @ c.normal_F > 0.95


def test_scanner_poses_face_the_surface_at_the_sweet_spot():
    scene = make_scene(box(2000.0, 1000.0, 1000.0))
    st = station_below(-1300.0)
    cells, rows, cols = raster_cells(scene, st, 848.2, (0.0, 1000.0), 6000.0, FOOTPRINT)
    ik = AnalyticIK(ArmConfig())
    raster = plan_station(st, cells, rows, cols, setup(ik), np.radians([0.0, 90.0, 0.0, 90.0, 0.0, 0.0]))
    assert raster.poses, "the wall of a 1 m box is within reach"
    assert len(raster.poses) + len(raster.unreached) == len(cells)
    kin = ArmKinematics(ArmConfig())
    for p in raster.poses:
        R = p.T_F_S[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
        assert np.linalg.det(R) == pytest.approx(1.0)
        view = R[:, 2]
        assert np.linalg.norm(p.cell.point_F - p.T_F_S[:3, 3]) == pytest.approx(442.0)
        np.testing.assert_allclose(p.T_F_S[:3, 3] + 442.0 * view, p.cell.point_F, atol=1e-9)
        incidence = math.degrees(math.acos(np.clip(-view @ p.cell.normal_F, -1, 1)))
        assert incidence <= 45.0 + 1e-6
        assert incidence == pytest.approx(math.degrees(p.tilt_rad), abs=1e-6)
        assert kin.within_limits(p.joints_rad)
        # the joints really put the scanner there
        T = F.planar_pose(st.x_mm, st.y_mm, st.heading_rad) @ CELL.T_V2_B @ kin.forward(
            p.joints_rad) @ CELL.T_E_S
        np.testing.assert_allclose(T, p.T_F_S, atol=1e-6)


def test_unreachable_region_is_reported_not_skipped():
    scene = make_scene(box(2000.0, 1000.0, 4000.0))  # a 4 m wall: the arm on its AGV cannot reach the top
    st = station_below(-1300.0)
    cells, rows, cols = raster_cells(scene, st, 848.2, (0.0, 4000.0), 8000.0, FOOTPRINT)
    raster = plan_station(st, cells, rows, cols, setup(AnalyticIK(ArmConfig())), np.radians([0, 90, 0, 90, 0, 0]))
    assert raster.unreached and raster.poses
    assert len(raster.poses) + len(raster.unreached) == len(cells)
    assert all("no joint solution" in u.reason for u in raster.unreached)
    assert min(u.cell.point_F[2] for u in raster.unreached if u.cell.normal_F[1] < -0.9) > 1000.0
    assert max(p.cell.point_F[2] for p in raster.poses) < 2000.0


def test_order_moves_the_joints_no_more_than_the_plain_snake():
    scene = make_scene(box(2000.0, 1000.0, 1000.0))
    st = station_below(-1300.0)
    cells, rows, cols = raster_cells(scene, st, 848.2, (0.0, 1000.0), 6000.0, FOOTPRINT)
    raster = plan_station(st, cells, rows, cols, setup(AnalyticIK(ArmConfig())), np.radians([0, 90, 0, 90, 0, 0]))
    poses = list(raster.poses)
    snake = [poses[k] for k in _snake([(p.cell.row, p.cell.col) for p in poses], column_major=True)]
    assert raster.joint_travel_rad == pytest.approx(_travel([p.joints_rad for p in poses]))
    assert raster.joint_travel_rad <= _travel([p.joints_rad for p in snake]) + 1e-9
    # consecutive poses are raster neighbours (boustrophedon): never a jump over a whole column
    for a, b in zip(poses[:-1], poses[1:], strict=True):
        assert abs(a.cell.col - b.cell.col) <= 1 or abs(a.cell.row - b.cell.row) <= 1


def test_snake_order():
    cells = [(r, c) for c in range(3) for r in range(2)]
    order = _snake(cells, column_major=True)
    assert [cells[i] for i in order] == [(0, 0), (1, 0), (1, 1), (0, 1), (0, 2), (1, 2)]


def test_closed_form_ik_reaches_random_poses_within_limits():
    ik = AnalyticIK(ArmConfig())
    kin = ik.kin
    rng = np.random.default_rng(3)
    for _ in range(200):
        q = np.clip(rng.uniform(kin.q_min, kin.q_max), -3.0, 3.0)
        T = kin.forward(q)
        sol = ik(T, q)
        assert sol is not None and kin.within_limits(sol)
        np.testing.assert_allclose(kin.forward(sol), T, atol=1e-6)
        np.testing.assert_allclose(sol, q, atol=1e-6)  # seeded with the answer, it returns that branch


def test_closed_form_ik_agrees_with_the_numerical_one():
    ik = AnalyticIK(ArmConfig())
    kin = ik.kin
    T = kin.forward(np.radians([10.0, 80.0, 30.0, 60.0, -20.0, 5.0]))
    assert kin.inverse(T, np.zeros(6)) is not None and ik(T, np.zeros(6)) is not None
    far = T.copy()
    far[:3, 3] = [2000.0, 0.0, 500.0]  # beyond any reach
    assert ik(far, np.zeros(6)) is None


def test_closed_form_ik_refuses_other_geometry():
    with pytest.raises(ValueError, match="UR-style"):
        AnalyticIK(ArmConfig(dh_alpha_rad=(0.0,) * 6))


def test_reach_prefilter_never_rejects_a_reachable_pose():
    ik = AnalyticIK(ArmConfig())
    rng = np.random.default_rng(9)
    qs = np.clip(rng.uniform(ik.kin.q_min, ik.kin.q_max, (300, 6)), -3.0, 3.0)
    T = np.stack([ik.kin.forward(q) for q in qs])
    assert ik.maybe_reachable(T).all()
    far = T.copy()
    far[:, 0, 3] += 3000.0
    assert not ik.maybe_reachable(far).any()
