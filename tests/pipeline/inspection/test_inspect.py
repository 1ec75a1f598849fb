"""Inspection: signed deviation from CAD on shapes with known answers, checked against an independent
computation (scipy KD-tree over a dense sampling of the mesh, exact point-to-triangle distance)."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial import cKDTree
from tandemscan.config.models import InspectionConfig, RegionConfig
from tandemscan.pipeline.geometry.frames import from_rotvec, invert, transform_points
from tandemscan.pipeline.inspection import inspect
from tandemscan.pipeline.inspection.inspect import (
    CadSurface,
    DeviationStats,
    InspectionCriteria,
    InspectionError,
    ToleranceResult,
    inspect_cloud,
)

# Far from the origin on purpose: part-scale coordinates are where float32 rounding would show.
CENTRE = np.array([1400.0, -650.0, 900.0])
UM = 1e-3  # one micrometre in mm


def sphere_mesh(radius_mm=50.0, resolution=40):
    m = o3d.geometry.TriangleMesh.create_sphere(radius=radius_mm, resolution=resolution)
    m.translate(CENTRE)
    return m


def box_mesh(size=(400.0, 200.0, 100.0)):
    m = o3d.geometry.TriangleMesh.create_box(*size)
    m.translate(CENTRE)
    return m


def _closest_on_triangles(p, a, b, c):
    """Exact distance and closest point of points p to triangles (a, b, c), row by row, float64."""
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    h = np.einsum("ij,ij->i", p - a, n)
    q = p - h[:, None] * n
    # inside test on the projection: same side of all three edges
    inside = np.ones(len(p), bool)
    for u, v in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("ij,ij->i", np.cross(v - u, q - u), n) >= 0
    best_d = np.where(inside, np.abs(h), np.inf)
    best_c = np.where(inside[:, None], q, np.nan)
    for u, v in ((a, b), (b, c), (c, a)):
        e = v - u
        t = np.clip(np.einsum("ij,ij->i", p - u, e) / np.einsum("ij,ij->i", e, e), 0.0, 1.0)
        s = u + t[:, None] * e
        d = np.linalg.norm(p - s, axis=1)
        better = ~inside & (d < best_d)
        best_d = np.where(better, d, best_d)
        best_c = np.where(better[:, None], s, best_c)
    return best_d, best_c, n


def kdtree_signed_distances(points, mesh, spacing_mm=0.3):
    """Independent reference, exact by construction. Every triangle is sampled on a regular barycentric
    grid whose nodes lie within ``h <= spacing_mm`` of any point of it. With ``r`` the distance to the
    nearest sample, the closest surface point is within ``r`` of the query and has a node of its triangle
    within ``h``, so the triangles owning a sample within ``r + h`` (scipy KD-tree) include it; the exact
    point-to-triangle distance over those gives the distance, the closest triangle's normal the sign."""
    V = np.asarray(mesh.vertices, float)
    F = np.asarray(mesh.triangles)
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    longest = max(np.linalg.norm(u - v, axis=1).max() for u, v in ((a, b), (b, c), (c, a)))
    m = int(np.ceil(longest / spacing_mm))
    i, j = np.array([(i, j) for i in range(m + 1) for j in range(m + 1 - i)], float).T / m
    samples = (a[:, None] + i[:, None] * (b - a)[:, None] + j[:, None] * (c - a)[:, None]).reshape(-1, 3)
    owner = np.repeat(np.arange(len(F)), len(i))
    tree = cKDTree(samples)
    r, _ = tree.query(points)
    balls = tree.query_ball_point(points, r + longest / m)
    pairs = np.array([(q, t) for q, ball in enumerate(balls) for t in set(owner[ball].tolist())])
    q, tri = pairs[:, 0], F[pairs[:, 1]]
    d, cp, n = _closest_on_triangles(points[q], V[tri[:, 0]], V[tri[:, 1]], V[tri[:, 2]])
    best = np.full(len(points), np.inf)
    np.minimum.at(best, q, d)
    win = d == best[q]
    signed = np.zeros(len(points))
    signed[q[win]] = np.where(np.einsum("ij,ij->i", points[q] - cp, n)[win] < 0, -1.0, 1.0) * d[win]
    return signed


def sphere_points(n, radius_mm, offsets_mm, seed=1):
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return CENTRE + u * (radius_mm + offsets_mm)[:, None]


def test_sphere_known_offsets_within_chord_sag():
    R = 50.0
    mesh = sphere_mesh(R)
    V = np.asarray(mesh.vertices) - CENTRE
    F = np.asarray(mesh.triangles)
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    plane_dist = np.abs(np.einsum("ij,ij->i", V[F[:, 0]], n / np.linalg.norm(n, axis=1, keepdims=True)))
    sag = R - plane_dist.min()  # the mesh lies between the sphere and this far inside it
    rng = np.random.default_rng(2)
    offsets = rng.uniform(-0.8, 0.8, 3000)
    d = CadSurface(mesh).signed_distance(sphere_points(3000, R, offsets))
    assert np.all(d >= offsets - 1e-6) and np.all(d <= offsets + sag + 1e-6)
    # outside is positive and inside negative, on every point clearly off the mesh
    clear = np.abs(offsets) > sag + 0.01
    assert np.array_equal(np.sign(d[clear]), np.sign(offsets[clear]))


def test_sphere_agrees_with_independent_kdtree_within_one_micrometre():
    mesh = sphere_mesh(50.0)
    offsets = np.random.default_rng(3).normal(0.0, 0.3, 4000)
    pts = sphere_points(4000, 50.0, offsets, seed=4)
    ours = CadSurface(mesh).signed_distance(pts)
    ref = kdtree_signed_distances(pts, mesh)
    assert np.max(np.abs(ours - ref)) < UM
    a, b = DeviationStats.of(ours), DeviationStats.of(ref)
    for name in ("mean_mm", "sigma_mm", "rms_mm", "min_mm", "max_mm", "p5_mm", "p95_mm"):
        assert abs(getattr(a, name) - getattr(b, name)) < UM, name


def box_face_points(size, n_per_face, offsets_fn, margin=2.0, seed=5):
    """Points above (offset > 0) or below every face of the box, projections >= margin from the edges;
    returns points and their exact signed distances."""
    rng = np.random.default_rng(seed)
    size = np.asarray(size)
    pts, truth = [], []
    for axis in range(3):
        for side in (0.0, 1.0):
            uv = rng.uniform(0.0, 1.0, (n_per_face, 3)) * (size - 2 * margin) + margin
            off = offsets_fn(rng, n_per_face)
            uv[:, axis] = side * size[axis] + (off if side else -off)
            pts.append(uv + CENTRE)
            truth.append(off)
    return np.vstack(pts), np.concatenate(truth)


def test_box_known_offsets_faces_edges_corners_and_inside():
    size = (400.0, 200.0, 100.0)
    mesh = box_mesh(size)
    pts, truth = box_face_points(size, 500, lambda rng, n: rng.uniform(-1.5, 1.5, n))
    corner = CENTRE + np.array(size)
    extra = np.array([
        corner + [3.0, 4.0, 12.0],  # off a corner: Euclidean distance 13
        CENTRE + [200.0, -3.0, -4.0],  # off an edge: 5
        CENTRE + np.array(size) / 2,  # centre of the box: 50 below the top and bottom faces
    ])
    d = CadSurface(mesh).signed_distance(np.vstack([pts, extra]))
    np.testing.assert_allclose(d[:-3], truth, atol=0.5 * UM)
    np.testing.assert_allclose(d[-3:], [13.0, 5.0, -50.0], atol=0.5 * UM)
    ref = kdtree_signed_distances(pts, mesh, spacing_mm=2.0)
    assert np.max(np.abs(d[:-3] - ref)) < UM


def test_inside_out_closed_mesh_gives_the_same_signs():
    mesh = box_mesh()
    flipped = o3d.geometry.TriangleMesh(mesh.vertices, o3d.utility.Vector3iVector(np.asarray(mesh.triangles)[:, ::-1]))
    pts = CENTRE + np.array([[200.0, 100.0, 101.0], [200.0, 100.0, 99.0], [-2.0, 50.0, 50.0]])
    surface = CadSurface(flipped)
    assert surface.flipped and not CadSurface(mesh).flipped
    np.testing.assert_allclose(surface.signed_distance(pts), [1.0, -1.0, 2.0], atol=UM)
    np.testing.assert_allclose(surface.closest(pts).normals[0], [0, 0, 1], atol=1e-6)  # outward


def test_tolerance_shares_and_stats_by_hand():
    d = np.array([-0.3, -0.1, 0.0, 0.05, 0.1, 0.2, 0.25, -0.05])
    tol = ToleranceResult.of(d, -0.1, 0.1)
    assert tol.in_pct == pytest.approx(62.5) and tol.above_pct == pytest.approx(25.0)
    assert tol.below_pct == pytest.approx(12.5)
    s = DeviationStats.of(d)
    assert s.count == 8 and s.min_mm == -0.3 and s.max_mm == 0.25
    assert s.rms_mm == pytest.approx(np.sqrt(np.mean(d**2)))
    assert s.sigma_mm == pytest.approx(np.std(d, ddof=1))
    assert DeviationStats.of(np.array([])) is None
    with pytest.raises(InspectionError, match="above upper"):
        ToleranceResult.of(d, 0.2, 0.1)


def criteria(**kw) -> InspectionCriteria:
    """``[inspection]``'s defaults, but ``kw``, as :func:`inspect_cloud` takes them."""
    return InspectionCriteria.from_section(InspectionConfig(**kw))


def test_regions_and_best_fit_reported_apart():
    size = (400.0, 200.0, 100.0)
    mesh = box_mesh(size)
    pts, _ = box_face_points(size, 800, lambda rng, n: rng.normal(0.0, 0.01, n), margin=0.5)
    T_M_F = from_rotvec([0.30, -0.20, 0.15], np.radians([0.02, -0.03, 0.05]))  # a small misplacement
    measured = transform_points(T_M_F, pts)
    cfg = InspectionConfig(
        tolerance_lower_mm=-0.05,
        tolerance_upper_mm=0.05,
        regions=(
            RegionConfig(name="left half", min_mm=tuple(CENTRE - 10), max_mm=tuple(CENTRE + [200, 210, 110])),
            RegionConfig(name="nowhere", min_mm=(0, 0, 0), max_mm=(1, 1, 1)),
        ),
        best_fit_max_distance_mm=2.0,
    )
    res = inspect_cloud(measured, mesh, InspectionCriteria.from_section(cfg))
    assert res.stats.rms_mm > 0.1 and res.tolerance.in_pct < 60  # as measured: the misplacement shows
    fit = res.best_fit
    assert fit is not None and fit.converged
    # the fit undoes the misplacement: no point of the part moves by more than 2 um against the truth
    residual = transform_points(fit.T_F_M @ T_M_F, pts) - pts
    assert np.linalg.norm(residual, axis=1).max() < 2 * UM
    assert fit.translation_mm == pytest.approx(np.linalg.norm(invert(T_M_F)[:3, 3]), abs=0.01)
    assert fit.stats.rms_mm < 0.012 and fit.tolerance.in_pct > 99.9
    left, nowhere = res.regions
    assert left.name == "left half" and 0.3 * len(pts) < left.stats.count < 0.7 * len(pts)
    assert nowhere.stats is None and nowhere.tolerance is None
    # as-measured deviations are the raw ones, not the best-fit ones
    np.testing.assert_allclose(res.deviations_mm, CadSurface(mesh).signed_distance(measured))


def test_bad_input_is_a_clear_error():
    mesh = box_mesh()
    with pytest.raises(InspectionError, match="no points"):
        CadSurface(mesh).signed_distance(np.zeros((0, 3)))
    with pytest.raises(InspectionError, match="not finite"):
        CadSurface(mesh).signed_distance(np.array([[0.0, np.nan, 0.0]]))
    with pytest.raises(InspectionError, match=r"\(N, 3\)"):
        CadSurface(mesh).signed_distance(np.zeros((4, 2)))
    with pytest.raises(InspectionError, match="no triangles"):
        CadSurface(o3d.geometry.TriangleMesh())
    # a cloud too far off for the best fit still gets its as-measured result, with the reason noted
    far = inspect_cloud(CENTRE + [[1e4, 0, 0]] * 10, mesh, criteria(best_fit_max_distance_mm=1.0))
    assert far.best_fit is None and "only 0 points within 1.0 mm" in far.best_fit_note
    assert far.stats.min_mm == pytest.approx(1e4 - 400.0) and far.stats.mean_mm > 9000


def test_regions_from_mesh_material_groups(tmp_path):
    """An OBJ with two materials (two faces of a plate): one region per group, by closest triangle."""
    (tmp_path / "plate.mtl").write_text("newmtl left\nKd 1 0 0\nnewmtl right\nKd 0 1 0\n")
    (tmp_path / "plate.obj").write_text(
        "mtllib plate.mtl\nv 0 0 0\nv 100 0 0\nv 100 100 0\nv 0 100 0\nv 200 0 0\nv 200 100 0\n"
        "usemtl left\nf 1 2 3\nf 1 3 4\nusemtl right\nf 2 5 6\nf 2 6 3\n"
    )
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "plate.obj"))
    rng = np.random.default_rng(0)
    left = np.c_[rng.uniform(1, 99, 300), rng.uniform(1, 99, 300), np.full(300, 0.05)]
    right = np.c_[rng.uniform(101, 199, 500), rng.uniform(1, 99, 500), np.full(500, -0.2)]
    res = inspect_cloud(np.vstack([left, right]), mesh, criteria(regions=(), best_fit=False))
    assert len(res.regions) == 2
    by_count = sorted(res.regions, key=lambda r: r.stats.count)
    assert by_count[0].stats.count == 300 and by_count[0].stats.mean_mm == pytest.approx(0.05, abs=UM)
    assert by_count[1].stats.count == 500 and by_count[1].stats.mean_mm == pytest.approx(-0.2, abs=UM)
    assert all(r.name.startswith("mesh group") for r in res.regions)
    off = inspect_cloud(left, mesh, criteria(regions=(), best_fit=False, mesh_group_regions=False))
    assert off.regions == ()


def test_config_refuses_an_empty_band_and_bad_regions():
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="tolerance band is empty"):
        InspectionConfig(tolerance_lower_mm=0.0, tolerance_upper_mm=0.0)
    with pytest.raises(ValidationError, match="must be >= min_mm"):
        RegionConfig(name="r", min_mm=(0, 0, 0), max_mm=(1, -1, 1))


def test_signed_distances_asked_by_chunks_are_the_closest_points_ones(monkeypatch):
    """``CadSurface.signed_distance`` of a cloud of several chunks (``inspect.CLOSEST_CHUNK``) keeps only the
    distances: the same numbers as :meth:`CadSurface.closest`'s of the whole cloud."""
    monkeypatch.setattr(inspect, "CLOSEST_CHUNK", 1000)
    surface = CadSurface(sphere_mesh())
    rng = np.random.default_rng(4)
    p = rng.normal(size=(3500, 3)) * 30.0
    assert np.array_equal(surface.signed_distance(p), surface.closest(p).signed_mm)
