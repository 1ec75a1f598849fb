"""DeepMerge inputs: overlap extraction on a known pair, plane normals and the k x 14 point structure."""

from __future__ import annotations

import numpy as np
import pytest
from tandemscan.pipeline.deepmerge.features import (
    FeatureError,
    farthest_points,
    plane_normals,
    point_structure,
)
from tandemscan.pipeline.registration.overlap import (
    OverlapError,
    delta_from_covariance,
    extract_overlap,
    relative_covariance,
)


def _grid(x0: float, x1: float, step: float = 1.0) -> np.ndarray:
    xs = np.arange(x0, x1 + 1e-9, step)
    X, Y = np.meshgrid(xs, np.arange(0.0, 10.0 + 1e-9, step))
    return np.c_[X.ravel(), Y.ravel(), np.zeros(X.size)]


def test_overlap_of_two_shifted_strips_is_their_common_band():
    a = _grid(0.0, 20.0)                    # x in [0, 20]
    b = _grid(10.0, 30.0) + [0.0, 0.0, 0.3]  # x in [10, 30], 0.3 mm above
    ov = extract_overlap(a, b, delta_mm=0.5)
    assert set(np.unique(a[ov.source_idx, 0])) == set(np.arange(10.0, 21.0))
    assert set(np.unique(b[ov.target_idx, 0])) == set(np.arange(10.0, 21.0))
    assert ov.size == 11 * 11
    # below the 0.3 mm gap nothing overlaps; a huge delta takes everything
    assert extract_overlap(a, b, delta_mm=0.29).size == 0
    assert extract_overlap(a, b, delta_mm=100.0).size == len(a)


def test_overlap_rejects_bad_input():
    with pytest.raises(OverlapError):
        extract_overlap(np.zeros((4, 2)), np.zeros((4, 3)), 1.0)
    with pytest.raises(OverlapError):
        extract_overlap(np.zeros((4, 3)), np.zeros((4, 3)), 0.0)
    with pytest.raises(OverlapError):
        extract_overlap(np.full((4, 3), np.nan), np.zeros((4, 3)), 1.0)


def test_delta_follows_the_pose_uncertainty():
    cov = np.diag([0.1**2, 0.05**2, 0.05**2, 0.001**2, 0.002**2, 0.001**2])
    # 3 sigma of (0.1 mm + 0.002 rad * 200 mm) = 1.5 mm
    assert delta_from_covariance(cov, 200.0, sigmas=3.0, min_delta_mm=0.1) == pytest.approx(1.5)
    # a tiny uncertainty falls back to the floor
    assert delta_from_covariance(cov * 1e-6, 200.0, min_delta_mm=0.8) == 0.8
    np.testing.assert_allclose(relative_covariance(cov, cov), 2 * cov)
    with pytest.raises(OverlapError):
        delta_from_covariance(np.eye(3), 1.0)


def test_plane_normals_of_a_tilted_plane_are_exact_and_oriented():
    rng = np.random.default_rng(0)
    uv = rng.uniform(-50, 50, (400, 2))
    n_true = np.array([1.0, -2.0, 2.0]) / 3.0
    e1 = np.cross(n_true, [0, 0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n_true, e1)
    P = uv[:, :1] * e1 + uv[:, 1:] * e2 + [5.0, 6.0, 7.0]
    N = plane_normals(P, k=8, orient_to=n_true)
    np.testing.assert_allclose(N, np.tile(n_true, (len(P), 1)), atol=1e-9)
    N_flip = plane_normals(P, k=8, orient_to=-n_true)
    np.testing.assert_allclose(N_flip, -N, atol=1e-9)


def test_plane_normals_of_a_sphere_are_radial():
    rng = np.random.default_rng(1)
    v = rng.normal(size=(3000, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    P = 100.0 * v
    N = plane_normals(P, k=10, orient_to=[0, 0, 1.0])
    cos = np.abs(np.einsum("ij,ij->i", N, v))
    assert np.median(cos) > 0.999 and cos.min() > 0.99


def test_point_structure_hand_computed_on_four_points():
    P = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [4.0, 4.0, 0.0]])
    S = point_structure(P, k=3, centres=[0], orient_to=[0, 0, 1.0])
    assert S.shape == (1, 3, 14) and S.dtype == np.float32
    # local part: self, then (1,0,0) at distance 1, then (0,2,0) at distance 2; normals +z
    np.testing.assert_allclose(S[0, :, :3], [[0, 0, 0], [1, 0, 0], [0, 2, 0]])
    np.testing.assert_allclose(S[0, :, 3:6], np.tile([0, 0, 1.0], (3, 1)), atol=1e-7)
    np.testing.assert_allclose(S[0, :, 6], [0, 1, 2])
    # global part: centroid (1.25, 1.5, 0); farthest from (0,0,0) is (4,4,0) at distance sqrt(32)
    glob = np.r_[-1.25, -1.5, 0.0, 2.75, 2.5, 0.0, np.sqrt(32.0)]
    np.testing.assert_allclose(S[0, :, 7:], np.tile(glob, (3, 1)), atol=1e-6)


def test_farthest_points_matches_brute_force_and_errors_are_typed():
    rng = np.random.default_rng(2)
    P = rng.normal(size=(700, 3))
    c = np.arange(0, 700, 7)
    brute = np.argmax(np.linalg.norm(P[c][:, None] - P[None], axis=2), axis=1)
    np.testing.assert_array_equal(farthest_points(P, c, chunk=16), brute)
    with pytest.raises(FeatureError):
        point_structure(P[:2], k=3)
    with pytest.raises(FeatureError):
        point_structure(P[:, :2], k=3)
