"""Joint multi-view refinement: noiseless overlapping scans sampled from one grid (so that at the true poses
every overlap point has an exact partner), perturbed starts, and sliding surfaces (plane, cylinder)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from tandemscan.pipeline.geometry.frames import from_rotvec, invert, pose_error, transform_points
from tandemscan.pipeline.registration.correction import joint_scan
from tandemscan.pipeline.registration.icp import RefineError
from tandemscan.pipeline.registration.joint import (
    MIN_RAY_COSINES_SQ,
    JointScan,
    JointSettings,
    ray_variances,
    refine_jointly,
)
from tandemscan.pipeline.registration.mount_unknown import MountPrior
from tandemscan.pipeline.registration.pose_graph import ScanPrior, TransferPrior
from tandemscan.pipeline.registration.sampling import voxel_downsample

TIGHT = np.diag([1e-8] * 3 + [1e-12] * 3)
#: a head-on residual's sigma of a real scanner, so that the second-order fit of a sampled curve does not count
SCANNER_NOISE = JointSettings(iterations=20, tolerance_mm=1e-7, sigma_mm=0.05)
LOOSE = np.diag([1.0] * 3 + [np.radians(0.5) ** 2] * 3)


def bumpy(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A surface curved enough to fix all six degrees of freedom of a 150 mm patch (mm)."""
    return 10 * np.sin(x / 17.0) * np.cos(y / 13.0) + 6 * np.cos(x / 23.0 + y / 19.0)


def grid_scans(surface_W: np.ndarray, windows: list[tuple[float, float]], axis: int = 0,
               normals_W: np.ndarray | None = None):
    """Scans of the world points ``surface_W`` (mm) whose coordinate ``axis`` lies in each window, each in its
    own scanner frame (looking down -z from 400 mm above the window's centre), with the exact ``normals_W``
    or, without them, normals estimated from the points. Returns (truth, scans)."""
    truth, scans = [], []
    for lo, hi in windows:
        keep = (surface_W[:, axis] >= lo) & (surface_W[:, axis] <= hi)
        centre = np.zeros(3)
        centre[axis] = 0.5 * (lo + hi)
        T = from_rotvec(centre + [0, 0, 400.0], [np.pi, 0, 0])
        truth.append(T)
        P_S = transform_points(invert(T), surface_W[keep])
        scans.append(JointScan.from_points(P_S) if normals_W is None
                     else JointScan(P_S, normals_W[keep] @ T[:3, :3]))
    return truth, scans


def perturbed(T: np.ndarray, rng: np.random.Generator, t_mm: float, r_deg: float) -> np.ndarray:
    return from_rotvec(rng.normal(0, t_mm, 3), rng.normal(0, np.radians(r_deg), 3)) @ T


def test_noiseless_overlaps_recover_exact_poses_from_perturbed_starts():
    g = np.arange(0.0, 601.0, 2.0)
    x, y = np.meshgrid(g, np.arange(-100.0, 101.0, 2.0))
    surface = np.c_[x.ravel(), y.ravel(), bumpy(x.ravel(), y.ravel())]
    truth, scans = grid_scans(surface, [(0, 300), (150, 450), (300, 600), (100, 500)])
    rng = np.random.default_rng(3)
    stations = [0, 0, 1, 1]
    tracker = [truth[0]] + [perturbed(T, rng, 0.3, 0.05) for T in truth[1:]]
    priors = [ScanPrior(tracker[0], TIGHT, 0)] + [ScanPrior(T, LOOSE, k) for T, k in zip(tracker[1:], stations[1:],
                                                                                        strict=True)]
    transfers = [TransferPrior(1, np.array([300.0, 0, 400]), LOOSE)]
    start = [truth[0]] + [perturbed(T, rng, 0.3, 0.05) for T in truth[1:]]
    pairs = [(0, 1), (1, 2), (0, 3), (1, 3), (2, 3)]
    res = refine_jointly(scans, priors, pairs, start, transfers, settings=JointSettings(iterations=20,
                                                                                       tolerance_mm=1e-7))
    before = [pose_error(S, T)[0] for S, T in zip(start[1:], truth[1:], strict=True)]
    errors = [pose_error(P, T) for P, T in zip(res.poses, truth, strict=True)]
    assert min(before) > 0.1
    assert max(e[0] for e in errors) < 1e-4
    assert max(e[1] for e in errors) < np.radians(1e-5)
    assert res.rms_mm_after < 1e-5 < res.rms_mm_before
    assert res.pairs == len(pairs) and res.covariances.shape == (4, 6, 6)
    # the posterior is far tighter than the loose priors wherever the overlaps see the scan
    assert np.all(np.diagonal(res.covariances[1:], axis1=1, axis2=2)[:, :3] < 1e-3 * LOOSE[0, 0])


def test_pairs_that_moved_are_associated_anew_and_reach_the_exact_poses():
    """A start 1.3 mm off along a 2 mm grid pairs each point with its neighbour's partner: kept, those
    correspondences hold the estimate 0.04 mm off; found anew once the pair has moved, they are the exact ones."""
    x, y = np.meshgrid(np.arange(0.0, 601.0, 2.0), np.arange(-100.0, 101.0, 2.0))
    surface = np.c_[x.ravel(), y.ravel(), bumpy(x.ravel(), y.ravel())]
    truth, scans = grid_scans(surface, [(0, 300), (150, 450)])
    priors = [ScanPrior(truth[0], TIGHT, 0), ScanPrior(truth[1], LOOSE, 0)]
    start = [truth[0], from_rotvec([1.3, -0.3, 0.1], np.radians([0.02, -0.03, 0.05])) @ truth[1]]
    errors = {}
    for reassociate_mm in (None, 0.05):
        settings = JointSettings(max_distance_mm=1.5, iterations=20, tolerance_mm=1e-7, reassociate_mm=reassociate_mm)
        errors[reassociate_mm] = pose_error(refine_jointly(scans, priors, [(0, 1)], start, settings=settings).poses[1],
                                            truth[1])[0]
    assert errors[None] > 0.01
    assert errors[0.05] < 1e-6


def test_at_least_one_linearisation_is_asked_for():
    with pytest.raises(ValueError, match="at least one"):
        JointSettings(iterations=0)


@pytest.mark.slow
def test_the_posterior_from_a_misaligned_start_matches_the_spread_of_its_estimates():
    """Two noisy scans of one surface (0.03 mm along z), the second started 0.3 mm / 0.05 deg off (many times the
    noise), over 30 noise draws: the residuals' scale at the start is the misalignment's and weights the data that
    way, but the posterior is that of the noise at the refined poses, so it matches the estimates' spread about the
    truth (its standard deviations within 0.7-1.4 of the draws'; with the start's scale they were 13 times wider)."""
    x, y = np.meshgrid(np.arange(0.0, 451.0, 2.0), np.arange(-100.0, 101.0, 2.0))
    surface = np.c_[x.ravel(), y.ravel(), bumpy(x.ravel(), y.ravel())]
    truth = [grid_scans(surface, [window])[0][0] for window in ((0, 300), (150, 450))]
    priors = [ScanPrior(truth[0], TIGHT, 0), ScanPrior(truth[1], LOOSE, 0)]
    start = [truth[0], from_rotvec([0.3, -0.2, 0.25], np.radians([0.05, -0.03, 0.02])) @ truth[1]]
    errors, sigmas = [], []
    for draw in range(30):
        rng = np.random.default_rng(100 + draw)
        scans = [grid_scans(surface + np.c_[np.zeros((len(surface), 2)), rng.normal(0, 0.03, len(surface))],
                            [window])[1][0] for window in ((0, 300), (150, 450))]
        res = refine_jointly(scans, priors, [(0, 1)], start, settings=JointSettings(max_distance_mm=2.5))
        assert res.sigma_mm > 5 * res.noise_sigma_mm                  # the weights' sigma: the start's
        errors.append(world_error(res.poses[1], truth[1]))
        sigmas.append(np.sqrt(np.diagonal(res.covariances[1])))
    ratio = np.mean(sigmas, axis=0) / np.sqrt(np.mean(np.square(errors), axis=0))   # spread about the truth
    assert np.all((ratio > 0.7) & (ratio < 1.4)), ratio


def two_scans_of(surface_W: np.ndarray, normals_W: np.ndarray, slide: np.ndarray, seed: int):
    """Two scans, x in 0-300 and 150-450 mm, with exact normals (estimated ones tilt at the scan's edges and
    would observe a little of the slide). Scan 0 is fixed at the truth; scan 1's tracker pose errs by
    ``slide`` (a world motion about its origin, t mm then rotation vector rad) and it starts elsewhere.
    Returns truth, scans, priors, start."""
    truth, scans = grid_scans(surface_W, [(0, 300), (150, 450)], 0, normals_W)
    o = truth[1][:3, 3]
    about = from_rotvec(o, [0, 0, 0]) @ from_rotvec(slide[:3], slide[3:]) @ from_rotvec(-o, [0, 0, 0])
    tracker = about @ truth[1]
    priors = [ScanPrior(truth[0], TIGHT, 0), ScanPrior(tracker, LOOSE, 0)]
    start = [truth[0], perturbed(truth[1], np.random.default_rng(seed), 0.3, 0.05)]
    return truth, scans, priors, start


def world_error(P: np.ndarray, T: np.ndarray) -> np.ndarray:
    """``(t mm, rotation vector rad)`` of the world motion about ``T``'s origin that takes ``T`` to ``P``."""
    o = T[:3, 3]
    M = from_rotvec(-o, [0, 0, 0]) @ P @ invert(T) @ from_rotvec(o, [0, 0, 0])
    from scipy.spatial.transform import Rotation

    return np.r_[M[:3, 3], Rotation.from_matrix(M[:3, :3]).as_rotvec()]


def test_a_sliding_plane_leaves_its_in_plane_directions_to_the_priors():
    x, y = np.meshgrid(np.arange(0.0, 451.0, 2.0), np.arange(-100.0, 101.0, 2.0))
    plane = np.c_[x.ravel(), y.ravel(), np.zeros(x.size)]
    slide = np.r_[0.4, -0.3, 0.2, np.radians(0.02), -np.radians(0.03), np.radians(0.05)]
    truth, scans, priors, start = two_scans_of(plane, np.tile([0.0, 0, 1], (len(plane), 1)), slide, seed=1)
    res = refine_jointly(scans, priors, [(0, 1)], start, settings=SCANNER_NOISE)
    err = world_error(res.poses[1], truth[1])
    # the plane z = 0 fixes tz, rx, ry: back to the truth; tx, ty, rz stay where the tracker put them
    np.testing.assert_allclose(err[[2, 3, 4]], 0.0, atol=1e-5)
    np.testing.assert_allclose(err[[0, 1, 5]], slide[[0, 1, 5]], rtol=1e-3, atol=1e-6)
    sigma = np.sqrt(np.diagonal(res.covariances[1]))
    np.testing.assert_allclose(sigma[[0, 1, 5]], np.sqrt(np.diag(LOOSE))[[0, 1, 5]], rtol=1e-3)
    assert np.all(sigma[[2, 3, 4]] < 1e-2 * np.sqrt(np.diag(LOOSE))[[2, 3, 4]])


def test_a_sliding_cylinder_leaves_its_axis_to_the_priors():
    radius = 120.0
    x, a = np.meshgrid(np.arange(0.0, 451.0, 2.0), np.arange(-0.8, 0.8, 2.0 / radius))
    cylinder = np.c_[x.ravel(), radius * np.sin(a.ravel()), radius * np.cos(a.ravel()) - radius]
    slide = np.r_[0.5, 0.2, -0.3, np.radians(0.04), np.radians(0.02), -np.radians(0.03)]
    normals = np.c_[np.zeros(a.size), np.sin(a.ravel()), np.cos(a.ravel())]
    truth, scans, priors, start = two_scans_of(cylinder, normals, slide, seed=2)
    res = refine_jointly(scans, priors, [(0, 1)], start, settings=SCANNER_NOISE)
    # free: a slide along the axis and a turn about it (the axis runs along x, 520 mm below the scan origin)
    free = np.array([[1.0, 0, 0, 0, 0, 0], [0, -(400.0 + radius), 0, 1, 0, 0]]).T
    info = np.linalg.inv(LOOSE)
    # the data fix the rest at the truth, so the answer is the prior's closest point on the free plane
    expected = free @ np.linalg.solve(free.T @ info @ free, free.T @ info @ slide)
    err = world_error(res.poses[1], truth[1])
    np.testing.assert_allclose(err, expected, rtol=1e-3, atol=5e-5)   # first order: 520 mm x (3e-4 rad)^2 / 2
    assert abs(expected[3]) > 1e-4 and abs(expected[0]) > 0.1


def test_mount_estimate_and_input_checks():
    x, y = np.meshgrid(np.arange(0.0, 451.0, 3.0), np.arange(-100.0, 101.0, 3.0))
    surface = np.c_[x.ravel(), y.ravel(), bumpy(x.ravel(), y.ravel())]
    truth, scans = grid_scans(surface, [(0, 300), (150, 450)])
    priors = [ScanPrior(T, LOOSE, 0) for T in truth]
    mount = MountPrior(np.diag([0.01] * 3 + [1e-6] * 3))
    res = refine_jointly(scans, priors, [(0, 1)], truth, mount_prior=mount)
    assert res.mount is not None and res.mount.estimated == int(np.sum(res.mount.information_ratio >= 1.0))
    assert np.all(np.diag(res.mount.covariance) <= np.diag(mount.covariance) * (1 + 1e-6))
    with pytest.raises(RefineError, match="differ"):
        refine_jointly(scans, priors[:1], [(0, 1)], truth)
    with pytest.raises(RefineError, match="transfer priors"):
        refine_jointly(scans, priors, [(0, 1)], truth, [TransferPrior(0, np.zeros(3), LOOSE)])


def test_ray_variances_follow_the_cosine_between_ray_and_normal():
    n = np.tile([0.0, 0, 1], (3, 1))
    head_on = np.array([[0.0, 0, -400]] * 3)
    tilted = np.array([[0.0, np.sqrt(3.0), -1.0], [0.0, 1.0, -1.0], [1.0, 0, -1e-3]])  # 60 deg, 45 deg, grazing
    np.testing.assert_allclose(ray_variances(n, head_on, head_on), 1.0)
    np.testing.assert_allclose(ray_variances(n, tilted, head_on), [0.625, 0.75, 0.5], atol=1e-6)
    np.testing.assert_allclose(ray_variances(n, tilted[2:], tilted[2:]), MIN_RAY_COSINES_SQ / 2.0)


def test_a_centroid_of_several_points_counts_as_their_lower_noise():
    n = np.tile([0.0, 0, 1], (2, 1))
    head_on = np.array([[0.0, 0, -400]] * 2)
    grazing = np.array([[1.0, 0, -1e-3]] * 2)
    np.testing.assert_allclose(ray_variances(n, head_on, head_on, np.array([1.0, 3.0]), np.array([1.0, 1.0])),
                               [1.0, 2.0 / 3.0])
    np.testing.assert_allclose(ray_variances(n, grazing, grazing, np.array([4.0, 1.0]), np.array([4.0, 1.0])),
                               [MIN_RAY_COSINES_SQ / 8.0, MIN_RAY_COSINES_SQ / 2.0])


def test_the_joint_scan_counts_the_measured_points_each_thinned_point_averages():
    rng = np.random.default_rng(3)
    points = np.r_[rng.uniform(0, 20, (400, 3)), np.tile([[31.0, 31.0, 31.0]], (5, 1))]  # five in one 2 mm voxel
    scan = joint_scan(points, 2.0)
    np.testing.assert_array_equal(scan.points_S, voxel_downsample(points, 2.0))
    assert scan.counts.sum() == len(points) and scan.counts.min() >= 1
    assert scan.counts[np.flatnonzero(np.all(scan.points_S == 31.0, axis=1))].tolist() == [5.0]
    assert scan.counts_at(np.array([0, 1])).shape == (2,) and JointScan(points, points).counts_at(np.array([0])) is None


@pytest.mark.slow
def test_points_that_average_more_measurements_weigh_more_and_the_estimate_is_tighter():
    """Scan 0's thinned points are centroids of nine measured points (a third of one point's noise), and so are
    scan 1's on one half of it; on the other half scan 1 has single points. The residuals there vary five times
    as much, and weighted by the counts (``JointScan.counts``) scan 1's pose errs about a quarter less over noise
    draws (expected 0.75 of the RMS, measured 0.83) than with every residual weighted alike. The Huber weights
    are off: they also cut the noisier residuals, and the comparison is the variance model's alone."""
    all_weighted = JointSettings(max_distance_mm=2.5, huber_k=1e6)
    x, y = np.meshgrid(np.arange(0.0, 451.0, 2.0), np.arange(-100.0, 101.0, 2.0))
    surface = np.c_[x.ravel(), y.ravel(), bumpy(x.ravel(), y.ravel())]
    windows = ((0, 300), (150, 450))
    truth = [grid_scans(surface, [window])[0][0] for window in windows]
    priors = [ScanPrior(truth[0], TIGHT, 0), ScanPrior(truth[1], LOOSE, 0)]
    in_1 = (surface[:, 0] >= 150) & (surface[:, 0] <= 450)
    counts_1 = np.where(surface[in_1, 0] < 300, 9.0, 1.0)
    errors = {"counts": [], "alike": []}
    for draw in range(20):
        rng = np.random.default_rng(500 + draw)
        noisy = surface.copy()
        noisy[:, 2] += rng.normal(0, 0.09, len(surface)) * np.where(surface[:, 0] < 300, 1.0 / 3.0, 1.0)
        noisy_0 = surface.copy()
        noisy_0[:, 2] += rng.normal(0, 0.03, len(surface))          # nine points of 0.09 mm each
        scan_0 = grid_scans(noisy_0, [windows[0]])[1][0]
        scan_1 = grid_scans(noisy, [windows[1]])[1][0]
        for label, counts in (("counts", counts_1), ("alike", None)):
            scans = [dataclasses.replace(scan_0, counts=None if counts is None else np.full(len(scan_0.points_S), 9.0)),
                     dataclasses.replace(scan_1, counts=counts)]
            res = refine_jointly(scans, priors, [(0, 1)], truth, settings=all_weighted)
            e = world_error(res.poses[1], truth[1])
            errors[label].append(np.r_[e[:3], e[3:] * 200.0])     # rotation at a 200 mm lever
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in errors.items()}
    assert rms["counts"] < 0.9 * rms["alike"], rms


def test_a_third_scan_of_the_same_place_with_a_free_pose_adds_no_information_on_the_second():
    """Scans 0 (fixed), 1 and 2 (loose priors) see the same surface points. Eliminating the unknown surface, scan
    2's free offset tells nothing more about scan 1 than the pair (0, 1) alone: the three pairs share each scan's
    noise and count 2 / 3 each. Counted at full weight they would make scan 1's posterior 1.5x too tight."""
    x, y = np.meshgrid(np.arange(0.0, 301.0, 3.0), np.arange(-100.0, 101.0, 3.0))
    surface = np.c_[x.ravel(), y.ravel(), bumpy(x.ravel(), y.ravel())]
    truth, scans = grid_scans(surface, [(0, 300)] * 3)
    priors = [ScanPrior(truth[0], TIGHT, 0)] + [ScanPrior(T, LOOSE, 0) for T in truth[1:]]
    two = refine_jointly(scans[:2], priors[:2], [(0, 1)], truth[:2], settings=SCANNER_NOISE)
    three = refine_jointly(scans, priors, [(0, 1), (0, 2), (1, 2)], truth, settings=SCANNER_NOISE)
    np.testing.assert_allclose(three.covariances[1], two.covariances[1], rtol=1e-3, atol=1e-12)
    assert np.all(np.diag(two.covariances[1]) < 1e-3 * np.diag(LOOSE))


def test_the_weights_sigma_is_that_of_two_points_seen_head_on_where_the_surface_is_seen_obliquely():
    """A plane rising 45 deg along x (bumped a little) under scanners looking down -z, each point 0.05 mm off
    along its ray: the squared cosines between rays and normals run from about 0.06 to 0.96, so a residual errs
    by less than two points seen head-on would (0.05 sqrt(2) = 0.0707 mm). The refinement takes its sigma
    (``sigma_mm``, ``noise_sigma_mm``) from the residuals whitened by their relative variance
    (:func:`ray_variances`) and finds the head-on figure (the residuals' own scale, 0.046 mm, weighed the data
    twice too much against the priors), and its estimate and posterior are those of the sigma given outright."""
    x, y = np.meshgrid(np.arange(0.0, 451.0, 2.0), np.arange(-100.0, 101.0, 2.0))
    surface = np.c_[x.ravel(), y.ravel(), x.ravel() + 0.3 * bumpy(x.ravel(), y.ravel())]
    truth, exact = grid_scans(surface, [(0, 300), (150, 450)])
    rng = np.random.default_rng(7)
    scans = []
    for s in exact:
        rays = s.points_S / np.linalg.norm(s.points_S, axis=1, keepdims=True)
        scans.append(JointScan.from_points(s.points_S + rays * rng.normal(0, 0.05, (len(rays), 1))))
    priors = [ScanPrior(truth[0], TIGHT, 0), ScanPrior(truth[1], LOOSE, 0)]
    res = refine_jointly(scans, priors, [(0, 1)], truth, settings=JointSettings(iterations=2))
    assert res.sigma_mm == pytest.approx(0.05 * np.sqrt(2), rel=0.08), res.sigma_mm
    assert res.noise_sigma_mm == pytest.approx(0.05 * np.sqrt(2), rel=0.08), res.noise_sigma_mm
    free = refine_jointly(scans, priors, [(0, 1)], truth, settings=JointSettings(iterations=2, huber_k=1e6))
    given = refine_jointly(scans, priors, [(0, 1)], truth,
                           settings=JointSettings(iterations=2, sigma_mm=free.sigma_mm, huber_k=1e6))
    np.testing.assert_allclose(free.covariances[1], given.covariances[1], rtol=1e-3)
    np.testing.assert_allclose(free.poses[1], given.poses[1], atol=1e-6)


def test_pairs_whose_points_err_together_widen_the_posterior_by_their_dispersion():
    """Nine scans of a bumpy patch on a 3 x 3 grid, half overlapping (20 pairs), scan 0 fixed, each point 0.03 mm
    off along z. On that noise alone the pairs' residuals scatter as it says (dispersion about 1) and the true
    pose errors' chi-square under the posterior is about its six degrees of freedom. With a smooth error of
    0.02 mm each scan's points share (a wave 60 mm long), the pairs scatter several times more than their
    points' noise says: counted as independent (the posterior before) the true errors' chi-square was 78 on
    average; counted at the pairs' dispersion about 10 (what a scan's own error shares with its pose stays
    unseen by any residual)."""
    g = np.arange(0.0, 301.0, 3.0)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    surface = np.c_[x, y, bumpy(x, y)]
    windows = [(a, b) for a in (0, 75, 150) for b in (0, 75, 150)]
    truth = [from_rotvec([a + 75.0, b + 75.0, 400.0], [np.pi, 0, 0]) for a, b in windows]
    pairs = [(i, j) for i in range(9) for j in range(i + 1, 9)
             if abs(windows[i][0] - windows[j][0]) < 150 and abs(windows[i][1] - windows[j][1]) < 150]
    priors = [ScanPrior(truth[0], TIGHT, 0)] + [ScanPrior(T, LOOSE, 0) for T in truth[1:]]

    def draws(shared_mm: float) -> tuple[float, list[float]]:
        chi2, dispersion = [], []
        for draw in range(3):
            rng = np.random.default_rng(50 + draw)
            scans = []
            for (a, b), T in zip(windows, truth, strict=True):
                keep = (x >= a) & (x <= a + 150) & (y >= b) & (y <= b + 150)
                k = rng.normal(0, 2 * np.pi / 60.0, 2)
                shared = shared_mm * np.sin(x[keep] * k[0] + y[keep] * k[1] + rng.uniform(0, 2 * np.pi))
                z = rng.normal(0, 0.03, keep.sum()) + shared
                scans.append(JointScan.from_points(transform_points(invert(T), surface[keep] + np.c_[0 * z, 0 * z, z])))
            res = refine_jointly(scans, priors, pairs, truth, settings=JointSettings(iterations=2))
            for P, T, C in zip(res.poses[1:], truth[1:], res.covariances[1:], strict=True):
                e = world_error(P, T)
                chi2.append(float(e @ np.linalg.solve(C, e)))
            dispersion.append(res.dispersion["0-0"])
        return float(np.mean(chi2)), dispersion

    chi2, dispersion = draws(0.0)
    assert 3.5 < chi2 < 9.0 and max(dispersion) < 1.5, (chi2, dispersion)
    chi2, dispersion = draws(0.02)
    assert chi2 < 12.0 and min(dispersion) > 3.0, (chi2, dispersion)
