"""Tracker stations (Eq. 16-18): exact solver = brute-force optimum; greedy chains are always valid."""

from __future__ import annotations

import itertools

import numpy as np
import open3d as o3d
import pytest
from tandemscan.config.models import CellConfig, PlanningConfig
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.raycast import make_scene
from tandemscan.pipeline.planning.parameters import PartPlanning
from tandemscan.pipeline.planning.tracker import (
    TrackerPlanningError,
    candidate_poses,
    cover_matrix,
    is_valid_chain,
    lp_lower_bound,
    solve_exact,
    solve_greedy,
)


def brute_force_optimum(cover: np.ndarray, first: int | None = None) -> int:
    """Fewest stations whose union covers all coverable points and that can be ordered into a chain."""
    need = cover.any(axis=0)
    for k in range(1, len(cover) + 1):
        for subset in itertools.combinations(range(len(cover)), k):
            if np.any(need & ~cover[list(subset)].any(axis=0)):
                continue
            if first is not None and first not in subset:
                continue
            if any(is_valid_chain(cover, perm) and (first is None or perm[0] == first)
                   for perm in itertools.permutations(subset)):
                return k
    raise AssertionError("unreachable: the full set is always a candidate")


def random_instance(rng: np.random.Generator, K: int, M: int, density: float) -> np.ndarray:
    cover = rng.random((K, M)) < density
    # make the intersection graph connected so a chain exists: station k shares a point with station k+1
    for k in range(K - 1):
        m = rng.integers(M)
        cover[k, m] = cover[k + 1, m] = True
    return cover


@pytest.mark.parametrize("seed", range(12))
def test_exact_equals_brute_force_on_small_instances(seed):
    rng = np.random.default_rng(seed)
    cover = random_instance(rng, K=7, M=int(rng.integers(8, 16)), density=float(rng.uniform(0.15, 0.35)))
    sol = solve_exact(cover, time_limit_s=10.0)
    assert sol is not None and sol.optimal
    assert is_valid_chain(cover, sol.chain)
    assert sol.count == brute_force_optimum(cover)
    assert sol.lower_bound == sol.count


@pytest.mark.parametrize("seed", range(6))
def test_exact_with_a_fixed_first_station_equals_brute_force(seed):
    rng = np.random.default_rng(50 + seed)
    cover = random_instance(rng, K=7, M=12, density=0.25)
    first = int(rng.integers(7))
    sol = solve_exact(cover, time_limit_s=10.0, first=first)
    assert sol is not None and sol.chain[0] == first and is_valid_chain(cover, sol.chain)
    assert sol.count == brute_force_optimum(cover, first)
    greedy = solve_greedy(cover, first=first)
    assert greedy.chain[0] == first and is_valid_chain(cover, greedy.chain)


def test_chain_condition_forces_more_stations_than_plain_set_cover():
    # stations 0 and 1 cover everything but share no point; station 2 bridges them
    cover = np.array([
        [1, 1, 0, 0],
        [0, 0, 1, 1],
        [0, 1, 1, 0],
    ], bool)
    assert lp_lower_bound(cover) == 2  # set cover alone takes {0, 1}
    sol = solve_exact(cover)
    assert sol is not None and sol.solver == "milp"  # the heuristic cannot prove 3 against the LP bound of 2
    assert sol.count == 3 and is_valid_chain(cover, sol.chain)
    assert sol.chain[1] == 2  # the bridge sits in the middle
    assert not is_valid_chain(cover, (0, 1, 2))


@pytest.mark.parametrize("seed", range(20))
def test_greedy_chain_is_always_valid(seed):
    rng = np.random.default_rng(100 + seed)
    cover = random_instance(rng, K=int(rng.integers(5, 60)), M=int(rng.integers(5, 200)),
                            density=float(rng.uniform(0.02, 0.3)))
    sol = solve_greedy(cover)
    assert is_valid_chain(cover, sol.chain)
    assert sol.lower_bound <= sol.count
    for a, b in itertools.pairwise(sol.chain):
        assert np.any(cover[a] & cover[b])


def test_uncoverable_points_are_reported_not_dropped():
    cover = np.array([[1, 1, 0], [0, 1, 0]], bool)
    sol = solve_greedy(cover)
    assert sol.uncovered == (2,)
    assert sol.chain == (0,)


def test_covers_that_cannot_chain_raise():
    cover = np.array([[1, 0], [0, 1]], bool)
    with pytest.raises(TrackerPlanningError, match="chained"):
        solve_greedy(cover)


def test_cover_by_field_of_view_range_facing_and_occlusion():
    view = PartPlanning.from_config(CellConfig(planning=PlanningConfig(tracker_best_range_mm=9000.0,
                                                                       tracker_min_range_mm=1000.0))).tracker_view
    T_V1_C = F.make_transform(np.eye(3), [0, 0, 0]) @ _camera_along_x()
    # a wall between x = 2000 and 2200, 1 m wide in y, 3 m tall
    wall = o3d.geometry.TriangleMesh.create_box(200.0, 1000.0, 3000.0)
    wall.translate([2000.0, -500.0, 0.0])
    scene = make_scene(wall)
    targets = np.array([
        [4000.0, 0.0, 500.0],      # behind the wall: occluded
        [4000.0, 2000.0, 0.0],     # beside the wall: seen
        [4000.0, 6000.0, 0.0],     # far outside the horizontal field of view
        [12000.0, 1000.0, 0.0],    # beyond d2
        [500.0, 0.0, 0.0],         # nearer than the least range
        [4000.0, 1500.0, 0.0],     # in view but turned away from the camera
    ])
    normals = np.tile([-1.0, 0.0, 0.0], (6, 1))
    normals[5] = [1.0, 0.0, 0.0]
    cand = np.array([[0.0, 0.0, 0.0]])
    cov = cover_matrix(cand, T_V1_C, targets, normals, scene, view)
    assert cov[0].tolist() == [False, True, False, False, False, False]
    cov_no_occlusion = cover_matrix(cand, T_V1_C, targets, normals, None, view)
    assert cov_no_occlusion[0, 0]


def _camera_along_x() -> np.ndarray:
    """Camera frame whose optical axis (z) is the chassis +x, image y down (-z), at floor height 0."""
    R = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    return F.make_transform(R, [0.0, 0.0, 0.0])


def test_candidate_headings_face_the_part():
    ring = np.array([[0.0, 5000.0], [5000.0, 0.0]])
    inward = np.array([[0.0, -1.0], [-1.0, 0.0]])
    cand = candidate_poses(ring, inward, (0.0, np.radians(30.0)))
    assert cand.shape == (4, 3)
    np.testing.assert_allclose(cand[:2, 2], [-np.pi / 2, np.pi])
    np.testing.assert_allclose(cand[2:, 2], [-np.pi / 2 + np.radians(30), np.pi + np.radians(30)])


def test_heuristic_matches_the_exact_optimum_on_stations_along_a_loop():
    """Stations seeing arcs of a loop of measuring points (the shape of a real part): the sweep is optimal."""
    M, width = 16, 4
    cover = np.zeros((M, M), bool)
    for k in range(M):
        cover[k, [(k + i) % M for i in range(width)]] = True
    greedy = solve_greedy(cover)
    exact = solve_exact(cover, time_limit_s=20.0)
    assert exact is not None and exact.optimal
    assert is_valid_chain(cover, greedy.chain)
    assert greedy.count == exact.count == 5  # each further arc adds 3 new points: 4 + 4 * 3 >= 16
