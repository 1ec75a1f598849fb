"""The voxel world map and the plan format."""

from __future__ import annotations

import numpy as np
import pytest
from tandemscan.daemon.plans import default_plan_path
from tandemscan.pipeline.planning.plan import MoveTracker, Plan, PlanError, Scan
from tandemscan.pipeline.stitching.worldmap import VoxelMap


def test_voxel_map_merges_points_per_voxel():
    vm = VoxelMap(voxel_mm=1.0)
    vm.add(np.array([[0.2, 0.2, 0.2], [0.4, 0.4, 0.4], [5.5, 0.5, 0.5]]))
    vm.add(np.array([[0.6, 0.6, 0.6], [-3.5, 0.5, 0.5]]))
    pts = vm.points()
    order = np.argsort(pts[:, 0])
    np.testing.assert_allclose(pts[order], [[-3.5, 0.5, 0.5], [0.4, 0.4, 0.4], [5.5, 0.5, 0.5]])
    assert sorted(vm.counts()) == [1, 1, 3]


def test_voxel_map_memory_is_bounded_by_the_surface_not_the_scans():
    rng = np.random.default_rng(0)
    scan = rng.uniform(0, 100, (20_000, 3)) * [1, 1, 0]
    vm = VoxelMap(2.0)
    vm.add(scan)
    size = len(vm)
    for _ in range(5):
        vm.add(scan + rng.normal(0, 0.01, scan.shape) * [1, 1, 0])
    assert len(vm) <= size * 1.01
    assert vm.counts().sum() == 6 * len(scan)


def test_a_scan_spread_far_apart_merges_as_its_parts_do():
    """A compact scan is voxelised by dense counting over its box; one whose box is huge (two patches 10 m
    apart) is sorted instead: both must give the same map."""
    rng = np.random.default_rng(1)
    a = rng.uniform(0, 50, (5000, 3)) * [1, 1, 0.1]
    b = a + [10_000.0, -3_000.0, 500.0]
    n = rng.normal(size=(10_000, 3))
    together, apart = VoxelMap(1.0), VoxelMap(1.0)
    together.add(a[:100], n[:100])                                # an existing map to merge into
    apart.add(a[:100], n[:100])
    together.add(np.r_[a, b], n)
    apart.add(b, n[5000:])
    apart.add(a, n[:5000])
    assert len(together) == len(apart) > 1000
    order_t, order_a = np.lexsort(together.points().T), np.lexsort(apart.points().T)
    np.testing.assert_allclose(together.points()[order_t], apart.points()[order_a])
    np.testing.assert_allclose(together.normals()[order_t], apart.normals()[order_a], atol=1e-12)
    np.testing.assert_array_equal(together.counts()[order_t], apart.counts()[order_a])


def test_voxel_map_keeps_normals_unit_length():
    vm = VoxelMap(1.0)
    vm.add(np.zeros((2, 3)) + 0.5, np.array([[0, 0, 1.0], [0, 0.1, 0.99]]))
    assert np.linalg.norm(vm.normals()[0]) == pytest.approx(1.0)


def test_shipped_plan_covers_a_band_with_two_transfers():
    plan = Plan.load(default_plan_path())
    assert plan.transfer_count >= 2 and plan.scan_count >= 12
    assert sum(s.kind == "move_measure" for s in plan.steps) >= 2


@pytest.mark.parametrize("suffix", [".toml", ".json"])
def test_plan_round_trips(tmp_path, suffix):
    plan = Plan(name="p", steps=[MoveTracker(x_mm=1, y_mm=2, heading_rad=0.5), Scan(label="a")])
    plan.save(tmp_path / f"plan{suffix}")
    assert Plan.load(tmp_path / f"plan{suffix}") == plan


def test_bad_plans_name_the_problem(tmp_path):
    bad = tmp_path / "p.toml"
    bad.write_text('name = "p"\n[[steps]]\nkind = "move_arm"\njoints_rad = [0, 1]\n')
    with pytest.raises(PlanError, match=r"p.toml: steps.0.move_arm.joints_rad"):
        Plan.load(bad)
    bad.write_text('name = "p"\nsteps = []\n')
    with pytest.raises(PlanError, match="at least one scan"):
        Plan.load(bad)
    with pytest.raises(PlanError, match="not found"):
        Plan.load(tmp_path / "nope.json")


def test_a_map_merged_scan_by_scan_equals_one_merged_at_once(monkeypatch):
    """The batch merged into the map after every scan (its arrays freed as they are gathered) or once at the
    end: the same voxels, counts and means."""
    from tandemscan.pipeline.stitching import worldmap

    rng = np.random.default_rng(4)
    scans = [(rng.uniform(-40, 40, (3000, 3)) * [1, 1, 0.05] + [7 * k, 0, 0], rng.normal(size=(3000, 3)))
             for k in range(6)]
    monkeypatch.setattr(worldmap, "_MIN_BATCH_VOXELS", 10**9)  # no merge until the map is read
    maps = []
    for every_scan in (True, False):
        vm = VoxelMap(1.0)
        for points, normals in scans:
            vm.add(points, normals)
            if every_scan:
                assert len(vm) > 0 and not vm._batch  # reading the map merges its batch
        maps.append(vm)
    each, once = maps
    assert len(each) == len(once) > 5000
    np.testing.assert_array_equal(each.counts(), once.counts())
    np.testing.assert_allclose(each.points(), once.points(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(each.normals(), once.normals(), rtol=0, atol=1e-9)


def test_maps_combined_equal_one_map_of_every_scan_and_are_left_empty():
    """Groups of scans merged into maps of their own and combined once: the voxels, counts and means of one map
    that took every scan (to the rounding of the sums' order); maps of another voxel edge are refused."""
    rng = np.random.default_rng(5)
    scans = [(rng.uniform(-40, 40, (3000, 3)) * [1, 1, 0.05] + [20 * k, 0, 0], rng.normal(size=(3000, 3)))
             for k in range(7)]   # neighbours overlap by half: voxels shared across the groups
    one = VoxelMap(1.0)
    groups = [VoxelMap(1.0) for _ in range(3)]
    for k, (points, normals) in enumerate(scans):
        one.add(points, normals)
        groups[k * 3 // len(scans)].add(points, normals)
    combined = VoxelMap.combined(groups)
    assert len(combined) == len(one) > 10_000 and len(combined) < sum(len(s[0]) for s in scans)
    np.testing.assert_array_equal(combined.counts(), one.counts())
    np.testing.assert_allclose(combined.points(), one.points(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(combined.normals(), one.normals(), rtol=0, atol=1e-9)
    assert all(len(g) == 0 for g in groups)   # their sums now live in the combined map only
    with pytest.raises(ValueError, match="cannot be combined"):
        VoxelMap.combined([VoxelMap(1.0), VoxelMap(2.0)])
    with pytest.raises(ValueError, match="no maps"):
        VoxelMap.combined([])


def test_a_tile_map_read_after_scans_outside_its_tile_is_unchanged():
    """Scans whose voxels all lie outside a tile's x window leave an empty batch: reading the map merges nothing."""
    rng = np.random.default_rng(6)
    inside, outside = rng.uniform(0, 9, (500, 3)), rng.uniform(20, 29, (500, 3))
    vm = VoxelMap(1.0, x_voxels=(0, 10), batch_share=0.25)
    vm.add(inside)
    before = vm.points().copy()
    vm.add(outside)
    np.testing.assert_array_equal(vm.points(), before)
    empty = VoxelMap(1.0, x_voxels=(0, 10))
    empty.add(outside)
    assert len(empty) == 0 and len(empty.points()) == 0
