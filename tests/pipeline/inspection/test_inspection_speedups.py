"""The shortcuts that keep a whole part's inspection fast give the answers of the long way: the closed-form
plane normal against numpy's eigh, the first-order best-fit deviations against a new query, the deviation
areas found on thinned centres against every point, and the coverage from the inspection's own closest
triangles against a new query."""

from __future__ import annotations

import gc
import weakref

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial import cKDTree
from tandemscan.pipeline.geometry.frames import from_rotvec, transform_points
from tandemscan.pipeline.inspection import deviation_areas
from tandemscan.pipeline.inspection.deviation_areas import DeviationCloud, even_centres, find_deviation_areas
from tandemscan.pipeline.inspection.deviation_maps import measured_triangles
from tandemscan.pipeline.inspection.inspect import SMALL_MOVE_MM, CadSurface, signed_distance_moved
from tandemscan.pipeline.registration.normals import smallest_eigenvectors
from test_deviation_areas import bell, plane


def _scatter(nb: np.ndarray) -> np.ndarray:
    c = nb - nb.mean(axis=1, keepdims=True)
    return np.einsum("nki,nkj->nij", c, c)


def _aligned(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.abs(np.einsum("ni,ni->n", u, v))


def test_closed_form_plane_normal_is_eighs_smallest_eigenvector():
    rng = np.random.default_rng(0)
    n = 5000
    # noisy local planes in every orientation, far from the origin, with a shape from flat to nearly isotropic
    spread = np.c_[rng.uniform(0.5, 3.0, n), rng.uniform(0.5, 3.0, n), rng.uniform(0.0, 0.4, n)]
    local = rng.normal(size=(n, 10, 3)) * spread[:, None, :]
    rot = np.linalg.qr(rng.normal(size=(n, 3, 3)))[0]
    nb = np.einsum("nij,nkj->nki", rot, local) + rng.uniform(-2000, 2000, (n, 1, 3))
    cov = _scatter(nb)
    ours = smallest_eigenvectors(cov)
    vals, vecs = np.linalg.eigh(cov)
    np.testing.assert_allclose(np.linalg.norm(ours, axis=1), 1.0, atol=1e-12)
    gap = (vals[:, 1] - vals[:, 0]) / vals[:, 2]
    well = gap > 1e-3  # where the smallest eigenvalue is separated the vector is defined (up to sign)
    assert well.mean() > 0.95
    assert _aligned(ours[well], vecs[well, :, 0]).min() > 1 - 1e-8
    # the residual of the eigen-equation holds everywhere, separated or not
    lam = np.einsum("ni,nij,nj->n", ours, cov, ours)
    assert np.abs(lam - vals[:, 0]).max() <= 1e-9 * vals[:, 2].max() + 1e-12 * np.abs(vals[:, 2]).max()


def test_closed_form_plane_normal_on_degenerate_neighbourhoods():
    line = np.c_[np.linspace(0, 5, 10), np.zeros(10), np.zeros(10)] + [100.0, 50.0, 3.0]
    same = np.tile([[7.0, -3.0, 2.0]], (10, 1))
    flat = np.c_[np.random.default_rng(1).uniform(0, 3, (10, 2)), np.zeros(10)]
    cov = _scatter(np.stack([line, same, flat]))
    ours = smallest_eigenvectors(cov)
    assert np.isfinite(ours).all()
    np.testing.assert_allclose(np.linalg.norm(ours, axis=1), 1.0, atol=1e-12)
    assert abs(ours[0, 0]) < 1e-9  # any normal of a line is across it
    assert abs(ours[2, 2]) == pytest.approx(1.0, abs=1e-12)


def _on_surface(mesh, rng, n):
    v = np.asarray(mesh.vertices)[np.asarray(mesh.triangles)]
    area = np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    t = rng.choice(len(v), n, p=area / area.sum())
    r = rng.uniform(size=(n, 2))
    r = np.where(r.sum(axis=1, keepdims=True) > 1, 1 - r, r)
    return v[t, 0] + r[:, :1] * (v[t, 1] - v[t, 0]) + r[:, 1:] * (v[t, 2] - v[t, 0])


def test_small_best_fit_move_updates_deviations_to_first_order():
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=400.0, resolution=60)
    mesh.translate([1400.0, -650.0, 900.0])
    box = o3d.geometry.TriangleMesh.create_box(600.0, 300.0, 200.0)  # edges and corners as well as faces
    box.translate([300.0, 200.0, -100.0])
    rng = np.random.default_rng(2)
    for m in (mesh, box):
        surface = CadSurface(m)
        pts = _on_surface(m, rng, 40_000) + rng.normal(0.0, 0.05, (40_000, 3))
        before = surface.closest(pts)
        T = from_rotvec([0.001, -0.0005, 0.0008], [2e-6, -1e-6, 1.5e-6])  # microns over the part
        assert np.linalg.norm(transform_points(T, pts) - pts, axis=1).max() < SMALL_MOVE_MM
        ours = signed_distance_moved(surface, pts, T, before)
        truth = surface.signed_distance(transform_points(T, pts))
        assert np.abs(ours - truth).max() < 2e-4  # float32 rounding of the scene: about 0.1 um
        big = from_rotvec([0.5, 0.0, 0.0], [0.0, 0.0, 0.0])  # half a millimetre: queried anew
        np.testing.assert_array_equal(signed_distance_moved(surface, pts, big, before),
                                      surface.signed_distance(transform_points(big, pts)))


def test_deviation_areas_screened_on_a_thinning_are_those_of_every_point():
    rng = np.random.default_rng(0)
    p, d = plane(rng, noise=0.04)
    d += (-bell(p, (100.0, 100.0), 30.0, 0.3) + bell(p, (220.0, 200.0), 20.0, 0.2)
          + bell(p, (60.0, 240.0), 9.0, 0.25) - bell(p, (250.0, 60.0), 7.0, 0.3))
    full = find_deviation_areas(DeviationCloud(p, d), -0.1, 0.1, smoothing_mm=4.0, min_area_mm2=50.0, screen=False)
    screened = find_deviation_areas(DeviationCloud(p, d), -0.1, 0.1, smoothing_mm=4.0, min_area_mm2=50.0, screen=True)
    assert len(full) == 4
    assert [(a.id, a.side, a.points) for a in screened] == [(a.id, a.side, a.points) for a in full]
    for a, b in zip(full, screened, strict=True):
        np.testing.assert_allclose(b.centroid_mm, a.centroid_mm, atol=1e-9)
        assert (b.area_mm2, b.extreme_mm, b.mean_mm) == pytest.approx((a.area_mm2, a.extreme_mm, a.mean_mm), abs=1e-12)
    half = DeviationCloud(p, 0.5 * d)
    assert find_deviation_areas(half, -0.1, 0.1, smoothing_mm=4.0, screen=True) == find_deviation_areas(
        half, -0.1, 0.1, smoothing_mm=4.0, screen=False)


def test_even_centres_keep_one_point_per_cube():
    p = np.random.default_rng(4).uniform(-50, 50, (20_000, 3))
    first = even_centres(p, 10.0)
    keys = np.floor(p / 10.0)
    assert len(first) == 1000 == len(np.unique(keys[first], axis=0))  # 10 x 10 x 10 cubes, all occupied
    q = np.random.default_rng(11).normal(0.0, 300.0, (120_000, 3)) + [1400.0, -650.0, 900.0]  # many chunks
    cell = np.floor(q / 3.0).astype(np.int64)
    cell -= cell.min(axis=0)
    size = cell.max(axis=0) + 1
    plain = np.unique((cell[:, 0] * size[1] + cell[:, 1]) * size[2] + cell[:, 2], return_index=True)[1]
    np.testing.assert_array_equal(even_centres(q, 3.0), plain)  # the first point of each cube, in cube order


def test_coverage_from_the_inspections_closest_triangles_is_a_new_querys():
    box = CadSurface(o3d.geometry.TriangleMesh.create_box(300.0, 300.0, 50.0))
    rng = np.random.default_rng(5)
    pts = rng.uniform([0, 0, 49.0], [300, 150, 51.5], (20_000, 3))
    c = box.closest(pts)
    np.testing.assert_array_equal(measured_triangles(box, triangle_ids=c.triangle_ids, signed_mm=c.signed_mm),
                                  measured_triangles(box, pts))


def test_points_within_a_sphere_are_the_kd_trees():
    from scipy.spatial import cKDTree
    from tandemscan.pipeline.inspection.alignment import within

    p = np.random.default_rng(6).uniform(-100, 100, (50_000, 3)) + [1400.0, -650.0, 900.0]
    tree = cKDTree(p)
    for centre, r in (([1400.0, -650.0, 900.0], 30.0), ([1490.0, -560.0, 990.0], 25.0), ([0.0, 0.0, 0.0], 5.0)):
        np.testing.assert_array_equal(within(p, centre, r), sorted(tree.query_ball_point(centre, r)))


def test_overlap_before_correction_on_the_corrected_scans_tree_is_its_own_trees():
    from tandemscan.pipeline.inspection.stitch_quality import RIGID_TOLERANCE_MM, overlap_quality, rigid_motion

    rng = np.random.default_rng(7)
    after = []
    for k in range(4):  # overlapping curved patches at part-scale coordinates
        xy = rng.uniform([80.0 * k, 0.0], [80.0 * k + 130.0, 120.0], (6000, 2))
        z = 2e-4 * (xy[:, 0] - 150.0) ** 2 + 1e-3 * xy[:, 1] ** 2 + rng.normal(0.0, 0.02, 6000)
        after.append(np.c_[xy, z] + [1200.0, -600.0, 800.0])
    moves = [from_rotvec(rng.normal(0.0, 1e-3, 3), rng.normal(0.0, 0.3, 3)) for _ in after]
    before = [transform_points(T, a) for T, a in zip(moves, after, strict=True)]  # tracker-only: rigidly off
    assert all(np.allclose(rigid_motion(a, b), np.linalg.inv(T), atol=1e-9)
               for a, b, T in zip(after, before, moves, strict=True))
    bent = [b + rng.normal(0.0, 20 * RIGID_TOLERANCE_MM, b.shape) for b in before]  # no rigid motion: own trees
    assert all(rigid_motion(a, b) is None for a, b in zip(after, bent, strict=True))
    ours, theirs = overlap_quality(before, after), overlap_quality(bent, after)
    assert len(ours) == 3 and [(p.i, p.points) for p in ours] == [(p.i, p.points) for p in theirs]
    for p, q in zip(ours, theirs, strict=True):
        assert p.rms_before_mm > 5 * p.rms_after_mm  # the moves show before correction
        assert p.rms_after_mm == q.rms_after_mm
        assert p.rms_before_mm == pytest.approx(q.rms_before_mm, rel=1e-3)  # 20 nm noise apart


def _local_deviation_unbounded(p, d, smoothing_mm, at, k=48, kk=8):
    """The average and surface share of every point of ``at`` from a plain k-nearest query (the long way)."""
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(p).query(p[at], k=k)
    inside = dist <= smoothing_mm
    return (d[idx] * inside).sum(axis=1) / inside.sum(axis=1), np.pi * (0.5 * (dist[:, kk] + dist[:, kk + 1]))**2 / 9


def test_local_deviation_searched_within_the_radius_is_the_plain_nearest_neighbours():
    from tandemscan.pipeline.inspection.deviation_areas import local_deviation

    rng = np.random.default_rng(8)
    p, d = plane(rng, noise=0.05)
    p = p + [1300.0, -700.0, 900.0] + np.c_[rng.uniform(-0.3, 0.3, (len(p), 2)), np.zeros(len(p))]  # no ties
    lone = rng.uniform([1300.0, -700.0, 20.0], [1600.0, -400.0, 60.0], (300, 3))  # fewer than 10 within 4 mm
    p, d = np.vstack([p, lone]), np.r_[d, rng.normal(0.0, 0.05, len(lone))]
    at = np.r_[rng.choice(len(p) - len(lone), 3000, replace=False), np.arange(len(p) - len(lone), len(p))]
    ours = local_deviation(p, d, 4.0, at)
    smoothed, share = _local_deviation_unbounded(p, d, 4.0, at)
    np.testing.assert_array_equal(ours.smoothed_mm, smoothed)
    np.testing.assert_array_equal(ours.area_mm2, share)
    assert np.isfinite(ours.area_mm2).all() and (ours.area_mm2[-len(lone):] > 10.0).all()


def test_colour_map_z_buffer_picks_the_nearest_point_of_each_pixel_as_a_sort_would():
    from tandemscan.pipeline.inspection.deviation_maps import (
        DEVIATION_CMAP,
        STANDARD_VIEWS,
        MapPoints,
        _background,
        deviation_norm,
        render_view,
    )

    box = o3d.geometry.TriangleMesh.create_box(400.0, 200.0, 100.0).subdivide_midpoint(2)
    box.translate([1200.0, -600.0, 800.0])
    surface = CadSurface(box)
    rng = np.random.default_rng(9)
    p = _on_surface(box, rng, 60_000) + rng.normal(0.0, 0.05, (60_000, 3))
    values = rng.normal(0.0, 0.2, len(p))
    norm = deviation_norm(-0.1, 0.1)
    for view in (STANDARD_VIEWS["isometric"], STANDARD_VIEWS["top"]):
        ours = render_view(surface, MapPoints(p, values, spacing_mm=3.0), view, norm, 300, depth_margin_mm=400.0)
        bg = _background(surface, view, 300)  # the same splats, resolved by sorting (pixel, depth)
        x0, _, _, y1 = bg.extent_mm
        c, r = np.floor((p @ bg.r - x0) / bg.px).astype(int), np.floor((y1 - p @ bg.u) / bg.px).astype(int)
        depth = p @ bg.f - bg.depth0
        h, w = bg.t_hit.shape
        splat = int(min(6, max(1, np.ceil(1.5 * 3.0 / bg.px))))
        pix, dep, idx = [], [], []
        for dr in range(splat):
            for dc in range(splat):
                cc, rr = c + dc - splat // 2, r + dr - splat // 2
                ok = (cc >= 0) & (cc < w) & (rr >= 0) & (rr < h)
                ok[ok] &= depth[ok] <= bg.t_hit[rr[ok], cc[ok]] + 400.0
                pix.append(rr[ok] * w + cc[ok]), dep.append(depth[ok]), idx.append(np.flatnonzero(ok))
        pix, dep, idx = np.concatenate(pix), np.concatenate(dep), np.concatenate(idx)
        order = np.lexsort((dep, pix))
        first = np.unique(pix[order], return_index=True)[1]
        flat = bg.rgb.reshape(-1, 3).copy()
        flat[pix[order][first]] = DEVIATION_CMAP(norm(values))[:, :3][idx[order][first]]
        assert ours.coloured_px == len(first) > 1000
        np.testing.assert_array_equal(ours.rgb, flat.reshape(h, w, 3))


def test_whether_a_fit_moves_a_point_further_than_a_limit_is_the_brute_forces():
    from tandemscan.pipeline.inspection.inspect import _moves_further

    rng = np.random.default_rng(10)
    p = rng.uniform([-1500.0, -1000.0, 0.0], [1500.0, 1000.0, 1600.0], (50_000, 3))
    for _ in range(40):
        T = from_rotvec(rng.normal(0.0, 2e-6, 3), rng.normal(0.0, 2e-3, 3))
        largest = np.linalg.norm(transform_points(T, p) - p, axis=1).max()
        for limit in (0.5 * largest, 0.999 * largest, 1.001 * largest, 2.0 * largest):
            assert _moves_further(T, p, limit) == (largest > limit)


def test_closest_points_and_the_mapping_into_f_in_chunks_are_those_of_one_pass():
    from tandemscan.pipeline.geometry.frames import rotate_vectors
    from tandemscan.pipeline.inspection.inspect import CLOSEST_CHUNK, in_chunks

    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=400.0, resolution=40)
    mesh.translate([1400.0, -650.0, 900.0])
    surface = CadSurface(mesh)
    rng = np.random.default_rng(12)
    n = CLOSEST_CHUNK + 12_345  # two chunks, the second a part one
    pts = _on_surface(mesh, rng, n) + rng.normal(0.0, 0.5, (n, 3))
    whole = surface.closest(pts)
    for part in (slice(0, 1000), slice(CLOSEST_CHUNK - 500, CLOSEST_CHUNK + 500), slice(n - 1000, n)):
        alone = surface.closest(pts[part])  # in one chunk of its own
        for f in ("points_mm", "normals", "triangle_ids", "signed_mm"):
            np.testing.assert_array_equal(getattr(whole, f)[part], getattr(alone, f))
    T = from_rotvec([0.1, -0.2, 0.3], [10.0, -20.0, 30.0])
    np.testing.assert_array_equal(in_chunks(transform_points, T, pts), transform_points(T, pts))
    np.testing.assert_array_equal(in_chunks(rotate_vectors, T, whole.normals), rotate_vectors(T, whole.normals))


def test_placed_scans_map_each_scan_by_its_pose_when_read():
    """The stitch views' scans placed by one pose each (the tracker's, the corrected) or all by one (W into F):
    the same points as placing them at once, a scan at a time, and a pose missing is refused."""
    from tandemscan.pipeline.inspection.inspection_job import PlacedScans

    rng = np.random.default_rng(3)
    scans = [rng.normal(0, 100, (n, 3)) for n in (5, 0, 17)]
    poses = [from_rotvec(rng.normal(0, 50, 3), rng.normal(0, 0.3, 3)) for _ in scans]
    placed = PlacedScans(scans, poses)
    assert len(placed) == 3
    for k in range(3):
        np.testing.assert_array_equal(placed[k], transform_points(poses[k], scans[k]))
    T = from_rotvec([1.0, 2.0, 3.0], [0.1, 0.0, 0.2])
    moved = PlacedScans(placed, T)  # one pose for all, over scans that are themselves placed when read
    np.testing.assert_allclose(moved[2], transform_points(T @ poses[2], scans[2]), atol=1e-9)
    assert [len(s) for s in moved[0:3]] == [5, 0, 17]
    with pytest.raises(ValueError, match="3 scans but 2 poses"):
        PlacedScans(scans, poses[:2])


def test_points_near_the_screening_centres_are_found_chunk_by_chunk():
    rng = np.random.default_rng(5)
    p = rng.uniform(0, 200, (30_000, 3))
    centres = rng.uniform(0, 200, (2 * deviation_areas._BALL_CHUNK + 17, 3))  # three chunks, the last short
    within = deviation_areas._within(deviation_areas.kd_tree(p), centres, 6.0)
    nearest = cKDTree(centres).query(p)[0]
    np.testing.assert_array_equal(within, np.flatnonzero(nearest <= 6.0))
    assert 0 < len(within) < len(p)


def test_a_clouds_tree_and_screening_are_built_once_for_every_band_and_go_with_it(monkeypatch):
    """The areas at the band and at a narrower (guard) band found on one DeviationCloud are those of a fresh one
    each time, and its KD tree and coarse screening are built once for both; once the caller drops the cloud, its
    points are freed (nothing kept them: a whole part's are hundreds of MB)."""
    rng = np.random.default_rng(0)
    p, d = plane(rng, noise=0.04)
    d += -bell(p, (100.0, 100.0), 30.0, 0.3) + bell(p, (220.0, 200.0), 20.0, 0.2)
    trees, screenings = [], []  # the cloud's trees (not the areas' own small ones), the screenings
    tree, screening, n = deviation_areas.cKDTree, deviation_areas._screening, len(p)
    monkeypatch.setattr(deviation_areas, "cKDTree",
                        lambda points, *a, **k: trees.append(len(points) == n) or tree(points, *a, **k))
    monkeypatch.setattr(deviation_areas, "_screening", lambda *a: screenings.append(1) or screening(*a))
    cloud = DeviationCloud(p, d)
    for lo, hi in ((-0.1, 0.1), (-0.08, 0.08), (-0.09, 0.09)):
        fresh = find_deviation_areas(DeviationCloud(p, d), lo, hi, smoothing_mm=4.0, screen=True)
        assert fresh and find_deviation_areas(cloud, lo, hi, smoothing_mm=4.0, screen=True) == fresh
    assert sum(trees) == 3 + 1 and len(screenings) == 3 + 1  # a fresh cloud's each time, the shared one's once
    freed = weakref.ref(p), weakref.ref(d)
    del p, d, cloud
    gc.collect()
    assert [r() for r in freed] == [None, None]


def test_nearest_even_centre_searched_within_a_cubes_diagonal_is_the_plain_nearest():
    from tandemscan.pipeline.geometry.units import box_mm
    from tandemscan.pipeline.inspection.point_uncertainty import _nearest_centre

    rng = np.random.default_rng(3)
    xy = rng.uniform(-1500.0, 1500.0, (60_000, 2))  # a curved sheet at part scale, some cubes nearly empty
    p = np.c_[xy, 3e-4 * xy[:, 0] ** 2 - 2e-4 * xy[:, 1] ** 2 + rng.normal(0.0, 0.05, len(xy))] + [250.0, -40.0, 900.0]
    lo, hi = box_mm(p)
    assert np.array_equal(lo, p.min(axis=0)) and np.array_equal(hi, p.max(axis=0))
    for cell in (17.4, 45.0, 120.0):
        centres = even_centres(p, cell)
        assert np.array_equal(_nearest_centre(p, centres, cell), cKDTree(p[centres]).query(p)[1])
    assert np.array_equal(_nearest_centre(p, np.arange(len(p)), 0.1), np.arange(len(p)))


def test_alignment_variance_a_chunk_at_a_time_is_one_pass():
    from tandemscan.pipeline.inspection.point_uncertainty import ROWS_AT_ONCE, AlignmentCovariance, _alignment_variance

    rng = np.random.default_rng(4)
    n = 3 * ROWS_AT_ONCE + 17
    p, normals = rng.uniform(-1000.0, 1000.0, (n, 3)), rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    a = rng.normal(size=(6, 6))
    cov = AlignmentCovariance(a @ a.T * 1e-4, np.array([10.0, -20.0, 300.0]))
    j = np.hstack([normals, np.cross(p - cov.centre_mm, normals)])
    out = _alignment_variance(p, normals, cov)
    assert np.array_equal(out, np.einsum("ij,ij->i", j @ cov.covariance, j))
    assert np.allclose(out, np.einsum("ij,jk,ik->i", j, cov.covariance, j), rtol=1e-12, atol=0.0)


def test_overlap_quality_places_each_scan_once():
    from tandemscan.pipeline.inspection.inspection_job import PlacedScans
    from tandemscan.pipeline.inspection.stitch_quality import overlap_quality

    rng = np.random.default_rng(5)
    scans = []
    for k in range(5):  # overlapping patches, each in a scanner frame of its own
        xy = rng.uniform([60.0 * k, 0.0], [60.0 * k + 100.0, 100.0], (3000, 2))
        scans.append(np.c_[xy, 1e-3 * xy[:, 1] ** 2 + rng.normal(0.0, 0.02, len(xy))])
    poses = [from_rotvec(rng.normal(0.0, 1e-4, 3), rng.normal(0.0, 0.1, 3)) for _ in scans]

    class Counted(PlacedScans):
        def __init__(self, *args):
            super().__init__(*args)
            self.asked: list[int] = []

        def __getitem__(self, i):
            self.asked.append(i)
            return super().__getitem__(i)

    before, after = Counted(scans, poses), Counted(scans, np.eye(4))
    pairs = overlap_quality(before, after)
    assert [p.i for p in pairs] == [0, 1, 2, 3] and all(p.rms_before_mm > p.rms_after_mm for p in pairs)
    assert after.asked == [0, 1, 2, 3, 4] and before.asked == [0, 1, 2, 3, 4]
    placed = [[transform_points(T, s) for s, T in zip(scans, poses, strict=True)], [np.asarray(s) for s in scans]]
    assert pairs == overlap_quality(*placed)  # the same figures as from the scans placed beforehand


def test_a_scan_cover_prepared_finds_its_extents_unasked_and_answers_as_one_found_when_asked():
    import time

    from tandemscan.pipeline.inspection.point_uncertainty import ScanCover

    rng = np.random.default_rng(6)
    scans = [rng.uniform([100.0 * k, 0.0, 0.0], [100.0 * k + 150.0, 100.0, 1.0], (4000, 3)) for k in range(6)]

    def cover() -> ScanCover:
        return ScanCover(scans, [np.eye(4)] * len(scans), np.full(len(scans), 40_000.0), np.zeros((len(scans), 3)),
                         np.arange(len(scans)))

    prepared, asked = cover().prepared(), cover()
    deadline = time.monotonic() + 30.0
    while "_found_extents" not in prepared.__dict__ and time.monotonic() < deadline:  # found on its own thread
        time.sleep(0.01)
    assert "_found_extents" in prepared.__dict__ and "_found_extents" not in asked.__dict__
    queries = rng.uniform([0.0, 0.0, 0.0], [650.0, 100.0, 1.0], (500, 3))
    for a, b in zip(prepared.shares(queries), asked.shares(queries), strict=True):
        assert np.array_equal(a, b)


def test_a_scan_cover_asked_from_several_threads_while_it_prepares_finds_its_extents_once(monkeypatch):
    """The scans' extents :meth:`ScanCover.prepared` starts finding on its own thread, asked at once from four more
    threads: found once, the others wait for them and get the same answers."""
    import threading

    from tandemscan.pipeline.inspection import point_uncertainty

    builds = []

    real = point_uncertainty.x_extents

    def slow_extents(*args, **kwargs):
        builds.append(threading.current_thread())
        threading.Event().wait(0.2)  # long enough for every thread to ask meanwhile
        return real(*args, **kwargs)

    monkeypatch.setattr(point_uncertainty, "x_extents", slow_extents)
    rng = np.random.default_rng(7)
    scans = [rng.uniform([100.0 * k, 0.0, 0.0], [100.0 * k + 150.0, 100.0, 1.0], (2000, 3)) for k in range(4)]
    cover = point_uncertainty.ScanCover(scans, [np.eye(4)] * 4, np.full(4, 8000.0), np.zeros((4, 3)),
                                        np.arange(4)).prepared()
    queries = rng.uniform([0.0, 0.0, 0.0], [450.0, 100.0, 1.0], (200, 3))
    answers = []
    askers = [threading.Thread(target=lambda: answers.append(cover.shares(queries))) for _ in range(4)]
    for t in askers:
        t.start()
    for t in askers:
        t.join(30.0)
    assert len(builds) == 1 and len(answers) == 4
    for top, w in answers[1:]:
        assert np.array_equal(top, answers[0][0]) and np.array_equal(w, answers[0][1])


def test_a_best_fits_uncertainty_asks_its_scan_cover_once_and_each_row_is_answered_as_alone(monkeypatch):
    """:meth:`JobUncertainty.evaluate` of a best fit finds the scans of its even centres and of the fit's points in
    one pass of the cover's slabs (:meth:`ScanCover.shares` asked once): a row's answer does not depend on the rows
    asked with it."""
    from tandemscan.pipeline.inspection.point_uncertainty import JobUncertainty, ScanCover
    from tandemscan.pipeline.registration.pose_covariance import PoseCovariance

    rng = np.random.default_rng(8)
    scans = [rng.uniform([700.0 * k, 0.0, 0.0], [700.0 * k + 900.0, 300.0, 0.0], (6000, 3)) for k in range(3)]
    origins = np.array([[700.0 * k + 450.0, 150.0, 450.0] for k in range(3)])
    cover = ScanCover(scans, [np.eye(4)] * 3, np.full(3, 60_000.0), origins, np.arange(3))
    asked = []
    real = ScanCover.shares

    def counted(self, points_W, *args):
        asked.append(len(points_W))
        return real(self, points_W, *args)

    monkeypatch.setattr(ScanCover, "shares", counted)
    C = np.diag([0.01**2] * 18)
    poses = PoseCovariance(np.arange(3), origins, np.eye(18), np.eye(18), C, "test")
    p = rng.uniform([0.0, 0.0, 0.0], [2300.0, 300.0, 0.0], (30_000, 3))
    n = np.tile([0.0, 0.0, 1.0], (len(p), 1))
    u = JobUncertainty(poses, cover, 0.05).evaluate(p, n, 2.0, np.eye(4), "best-fit", None, None)
    assert len(asked) == 1 and np.all(np.isfinite(u.expanded_mm)) and np.all(u.expanded_mm > 0.0)
    rows = rng.choice(len(p), 3000, replace=False)  # across the slabs of x
    together = real(cover, p[rows])
    for part in np.array_split(np.arange(len(rows)), 3):
        for whole, alone in zip(together, real(cover, p[rows[part]]), strict=True):
            assert np.array_equal(whole[part], alone)


def test_a_clouds_box_and_box_test_a_block_of_rows_at_a_time_are_those_of_whole_columns():
    from tandemscan.pipeline.geometry.units import BOX_ROWS, box_mm, in_box_mm

    rng = np.random.default_rng(9)
    p = rng.normal(0.0, 100.0, (2 * BOX_ROWS + 17, 3))
    p[BOX_ROWS + 5] = [1e4, -1e4, 3e3]  # the extremes in a later block
    lo, hi = box_mm(p)
    assert np.array_equal(lo, p.min(axis=0)) and np.array_equal(hi, p.max(axis=0))
    box = (np.array([-50.0, -80.0, -20.0]), np.array([60.0, 10.0, 90.0]))
    assert np.array_equal(in_box_mm(p, *box), np.all((p >= box[0]) & (p <= box[1]), axis=1))
    with pytest.raises(ValueError):
        box_mm(np.zeros((0, 3)))
