"""The NumPy/SciPy fine stage against Open3D as its anchor (normals, point-to-plane ICP from the same start),
and the NumPy PLY reader against Open3D's."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from tandemscan.pipeline.geometry.frames import from_rotvec, invert, pose_error, transform_points
from tandemscan.pipeline.io.cloud_io import CloudIOError, read_ply
from tandemscan.pipeline.io.export import write_ply
from tandemscan.pipeline.registration.icp import (
    Convergence,
    TargetCloud,
    evaluate_point_to_plane,
    icp_point_to_plane,
    iterate_point_to_plane,
    target_with_normals,
)
from tandemscan.pipeline.registration.normals import estimate_normals

REG = o3d.pipelines.registration


def surface(xy: np.ndarray) -> np.ndarray:
    """A doubly curved surface (mm) over ``xy``: waves plus a bend, no symmetry that lets ICP slide."""
    x, y = xy[:, 0], xy[:, 1]
    return np.c_[xy, 8 * np.sin(x / 25) * np.cos(y / 30) + 0.001 * x**2 + 0.02 * y]


def overlapping(seed: int = 0, n: int = 6000) -> tuple[np.ndarray, np.ndarray]:
    """Two independently sampled crops (x in [-80, 30] and [-30, 80]) of :func:`surface`, 0.02 mm noise."""
    rng = np.random.default_rng(seed)
    return tuple(surface(np.c_[rng.uniform(lo, hi, n), rng.uniform(-80, 80, n)]) + rng.normal(0, 0.02, (n, 3))
                 for lo, hi in ((-80.0, 30.0), (-30.0, 80.0)))


def _o3d(points: np.ndarray, normals: np.ndarray | None = None) -> o3d.geometry.PointCloud:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    if normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(normals)
    return pcd


def test_normals_are_open3ds_knn_normals_up_to_sign():
    _, target = overlapping()
    ours = target_with_normals(target, 20).normals
    pcd = _o3d(target)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    assert np.abs(np.einsum("ij,ij->i", ours, np.asarray(pcd.normals))).min() > 1 - 1e-9
    # a neighbourhood without spread gets a defined normal, not NaN
    flat = estimate_normals(np.zeros((30, 3)), 10)
    assert np.all(np.isfinite(flat)) and np.allclose(np.linalg.norm(flat, axis=1), 1.0)


def test_the_closed_form_normal_is_lapacks_smallest_eigenvector():
    """``normals.smallest_eigenvectors`` against ``numpy.linalg.eigh`` on sets from round blobs to thin plates far
    from the origin (world coordinates, mm): the same direction to 1e-12; a set on a line gets a normal of it."""
    from tandemscan.pipeline.registration.normals import scatter_matrices, smallest_eigenvectors

    rng = np.random.default_rng(4)
    X = rng.normal(size=(600, 20, 3)) * np.geomspace([1.0, 1.0, 1.0], [5.0, 2.0, 1e-4], 600)[:, None, :]
    X = X @ np.stack([from_rotvec([0, 0, 0], r)[:3, :3] for r in rng.normal(size=(600, 3))]) + 3000.0
    centred = X - X.mean(axis=1, keepdims=True)
    _, V = np.linalg.eigh(np.matmul(centred.transpose(0, 2, 1), centred))
    ours = smallest_eigenvectors(scatter_matrices(centred))
    assert np.abs(np.einsum("ij,ij->i", ours, V[:, :, 0])).min() > 1 - 1e-12
    line = np.outer(np.arange(20.0), [1.0, 2.0, 3.0])[None]
    n = smallest_eigenvectors(scatter_matrices(line - line.mean(axis=1, keepdims=True)))[0]
    assert np.linalg.norm(n) == pytest.approx(1.0) and abs(n @ [1.0, 2.0, 3.0]) < 1e-6   # a normal of the line


@pytest.mark.parametrize(("distance_mm", "iterations"), [(5.0, 50), (2.0, 50), (2.0, 3)])
def test_icp_gives_open3ds_transform_from_the_same_start(distance_mm, iterations):
    source, target = overlapping()
    T_true = from_rotvec([1.0, -0.8, 0.6], np.radians([0.5, -0.3, 0.4]))
    S = transform_points(invert(T_true), source)
    tgt = target_with_normals(target)
    start = from_rotvec([0.2, 0.1, -0.1], np.radians([0.05, 0.0, -0.05]))
    ours = iterate_point_to_plane(S, tgt, start, distance_mm, Convergence(1e-9, 1e-9, iterations))
    theirs = REG.registration_icp(_o3d(S), _o3d(target, tgt.normals), distance_mm, start,
                                  REG.TransformationEstimationPointToPlane(),
                                  REG.ICPConvergenceCriteria(1e-9, 1e-9, iterations)).transformation
    assert np.abs(ours - theirs).max() < 1e-9
    if iterations == 50:                           # converged: near the truth (from 0.6 deg, 1.4 mm)
        dt, dr = pose_error(ours, T_true)
        assert dt < 0.05 and np.degrees(dr) < 0.05


def test_open3ds_default_stopping_rule_stops_where_open3d_does():
    source, target = overlapping(seed=1)
    S = transform_points(from_rotvec([2.0, 1.0, -1.0], np.radians([1.0, 0.5, -0.5])), source)
    tgt = target_with_normals(target)
    ours = iterate_point_to_plane(S, tgt, np.eye(4), 5.0, Convergence(1e-6, 1e-6, 30))
    theirs = REG.registration_icp(_o3d(S), _o3d(target, tgt.normals), 5.0, np.eye(4),
                                  REG.TransformationEstimationPointToPlane(),
                                  REG.ICPConvergenceCriteria(1e-6, 1e-6, 30)).transformation
    assert np.abs(ours - theirs).max() < 1e-9


def test_the_fit_and_its_score_match_open3ds_evaluation():
    source, target = overlapping(seed=2)
    tgt = target_with_normals(target)
    fit = icp_point_to_plane(source, tgt, np.eye(4), 2.0)
    theirs = REG.evaluate_registration(_o3d(source), _o3d(target), 2.0, fit.transformation)
    assert fit.fitness == pytest.approx(theirs.fitness, abs=1e-12)
    assert fit.inliers == len(np.asarray(theirs.correspondence_set))
    assert 0.0 < fit.rmse_mm <= theirs.inlier_rmse               # along the normal, never above the distance
    none = evaluate_point_to_plane(source + 1000.0, tgt, np.eye(4), 2.0)
    assert none.inliers == 0 and none.fitness == 0.0 and none.rmse_mm == float("inf")


def test_a_target_cloud_keeps_its_normals_when_a_part_is_selected():
    _, target = overlapping()
    tgt = target_with_normals(target)
    assert target_with_normals(tgt) is tgt
    part = tgt.select(np.arange(0, len(tgt), 3))
    assert isinstance(part, TargetCloud) and len(part) == len(range(0, len(tgt), 3))
    assert np.array_equal(part.normals, tgt.normals[::3])
    assert part.tree.query(target[3])[1] == 1                      # the new tree indexes the part


@pytest.mark.parametrize("ascii_", [False, True])
def test_ply_reader_reads_what_open3d_reads(tmp_path, ascii_):
    rng = np.random.default_rng(4)
    points, normals = rng.normal(0, 50, (500, 3)), rng.normal(size=(500, 3))
    pcd = _o3d(points, normals)
    pcd.colors = o3d.utility.Vector3dVector(rng.uniform(size=(500, 3)))   # a property the reader skips
    o3d.io.write_point_cloud(str(tmp_path / "c.ply"), pcd, write_ascii=ascii_)
    P, N = read_ply(tmp_path / "c.ply")
    theirs = o3d.io.read_point_cloud(str(tmp_path / "c.ply"))
    assert np.array_equal(P, np.asarray(theirs.points)) and np.array_equal(N, np.asarray(theirs.normals))
    assert np.allclose(P, points, rtol=1e-5, atol=1e-4)             # Open3D's ASCII keeps 6 digits


def test_ply_reader_reads_a_mesh_and_our_own_files_and_refuses_broken_ones(tmp_path):
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=40.0)
    o3d.io.write_triangle_mesh(str(tmp_path / "m.ply"), mesh, write_ascii=True)
    P, N = read_ply(tmp_path / "m.ply")                  # vertices, then a face element the reader skips
    assert np.allclose(P, np.asarray(mesh.vertices)) and N is None
    points = np.random.default_rng(5).normal(0, 50, (100, 3))
    write_ply(tmp_path / "ours.ply", points, scalars={"deviation_mm": np.zeros(100)})
    assert np.array_equal(read_ply(tmp_path / "ours.ply")[0], points)
    data = (tmp_path / "ours.ply").read_bytes()
    (tmp_path / "short.ply").write_bytes(data[:-100])
    with pytest.raises(CloudIOError, match="truncated"):
        read_ply(tmp_path / "short.ply")
    write_ply(tmp_path / "empty.ply", np.empty((0, 3)))
    with pytest.raises(CloudIOError, match="no points"):
        read_ply(tmp_path / "empty.ply")
    o3d.io.write_point_cloud(str(tmp_path / "c.pcd"), _o3d(points))    # other formats still through Open3D
    assert np.allclose(read_ply(tmp_path / "c.pcd")[0], points)
