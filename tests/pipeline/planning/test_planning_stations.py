"""Measurement-AGV stations (Eq. 13-14) on a box and a cylinder, with hand-checked answers."""

from __future__ import annotations

import math

import numpy as np
import open3d as o3d
import pytest
from shapely.geometry import Point
from tandemscan.config.models import CellConfig, PlanningConfig
from tandemscan.pipeline.planning.parameters import PartPlanning
from tandemscan.pipeline.planning.stations import (
    StationPlanningError,
    floor_contour,
    place_stations,
    station_count,
)


def box_mesh(lx=2000.0, ly=1000.0, lz=1000.0) -> o3d.geometry.TriangleMesh:
    m = o3d.geometry.TriangleMesh.create_box(lx, ly, lz)
    m.translate([-lx / 2, -ly / 2, 0.0])
    return m


def placed(mesh: o3d.geometry.TriangleMesh, planning: PlanningConfig | None = None):
    """``mesh``'s stations on the default cell with ``planning`` (default: its own)."""
    cell = PartPlanning.from_config(CellConfig(planning=planning or PlanningConfig()))
    return place_stations(mesh, cell.spacing, cell.footprint)


def test_box_contour_and_stations_by_hand():
    layout = placed(box_mesh())
    assert layout.contour.area == pytest.approx(2000.0 * 1000.0, rel=1e-6)
    # D = (d3 + d4)/2 + w/2 = 400 + 400 = 800 mm; path = 6000 + 2 pi 800 mm
    assert layout.distance_mm == pytest.approx(800.0)
    length = 6000.0 + 2 * math.pi * 800.0
    assert layout.path.exterior.length == pytest.approx(length, rel=2e-3)
    # step in (p, p + m) = (600, 600 + 0.8 * 360): N in (12.4, 18.4) -> the fewest, 13
    assert len(layout.stations) == 13
    assert 600.0 < layout.step_mm < 888.0
    d3, d4, w = 300.0, 500.0, 800.0
    for st in layout.stations:
        dist = layout.contour.exterior.distance(Point(st.x_mm, st.y_mm))
        assert d3 + w / 2 < dist < d4 + w / 2
        assert dist == pytest.approx(800.0, abs=1.0)
    first = layout.stations[0]
    # the arm side faces the part: a short step towards the part comes closer to the contour
    for st in layout.stations:
        probe = st.xy + 100.0 * st.towards_part
        assert layout.contour.exterior.distance(Point(*probe)) < 800.0 - 50.0
    # on the long side below the box (y = -1300) the chassis drives along +x
    below = [s for s in layout.stations if abs(s.y_mm + 1300.0) < 1.0 and abs(s.x_mm) < 900.0]
    assert below and all(abs(s.heading_rad) < 1e-3 for s in below)
    assert first.arc_mm == 0.0


def test_cylinder_stations_by_hand():
    cyl = o3d.geometry.TriangleMesh.create_cylinder(radius=500.0, height=1000.0, resolution=128)
    cyl.translate([0.0, 0.0, 500.0])
    layout = placed(cyl)
    # circle of radius 1300: 8168 mm; N in (9.2, 13.6) -> 10 stations 817 mm apart
    assert len(layout.stations) == 10
    assert layout.step_mm == pytest.approx(2 * math.pi * 1300.0 / 10, rel=2e-3)
    for st in layout.stations:
        assert math.hypot(st.x_mm, st.y_mm) == pytest.approx(1300.0, abs=2.0)
        # heading is tangent: perpendicular to the radius, counter-clockwise
        radial = np.array([st.x_mm, st.y_mm]) / 1300.0
        assert abs(radial @ st.tangent) < 1e-2
        assert radial[0] * st.tangent[1] - radial[1] * st.tangent[0] > 0.99


def test_station_count_interval():
    assert station_count(10000.0, 600.0, 288.0) == 12  # 10000/12 = 833 in (600, 888)
    for length in (2000.0, 7777.0, 31000.0):
        n = station_count(length, 600.0, 288.0)
        assert 600.0 < length / n < 888.0
    with pytest.raises(StationPlanningError):
        station_count(0.0, 600.0, 288.0)


def test_keep_out_zone_and_floor_boundary_skip_stations_with_reason():
    zone = ((-3000.0, 800.0), (3000.0, 800.0), (3000.0, 3000.0), (-3000.0, 3000.0))  # all above the box
    planning = PlanningConfig(keep_out_xy_mm=(zone,))
    layout = placed(box_mesh(), planning)
    assert layout.skipped and all("keep-out" in why for _, why in layout.skipped)
    assert all(s.y_mm < 800.0 - 400.0 for s in layout.stations)
    tight = PlanningConfig(floor_xy_mm=(-1000.0, -1000.0, 1000.0, 1000.0))
    with pytest.raises(StationPlanningError, match="free floor"):
        placed(box_mesh(), tight)


def test_concave_part_contour_keeps_its_notch():
    a = box_mesh(3000.0, 1000.0, 500.0)
    b = box_mesh(1000.0, 3000.0, 500.0)
    b.translate([-1000.0, 1000.0, 0.0])  # an L shape
    contour = floor_contour(a + b)
    assert contour.area == pytest.approx(3000.0 * 1000.0 + 1000.0 * 2000.0, rel=1e-3)
    assert contour.convex_hull.area > contour.area * 1.1


def test_inconsistent_standoff_is_an_error():
    with pytest.raises(StationPlanningError, match="d4"):
        placed(box_mesh(), PlanningConfig(arm_standoff_min_mm=500.0, arm_standoff_max_mm=400.0))
