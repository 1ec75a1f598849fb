"""Fine ICP and the pose graph on synthetic scans with known drift across coordinate transfers."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from tandemscan.pipeline.geometry.frames import compose, from_rotvec, invert, pose_error
from tandemscan.pipeline.registration.icp import RefineError, icp_point_to_plane, point_to_plane_information
from tandemscan.pipeline.registration.pose_graph import PairEdge, ScanPrior, TransferPrior, refine_poses


def bumpy_surface(rng: np.random.Generator, n: int = 6000, size: float = 200.0) -> np.ndarray:
    xy = rng.uniform(-size / 2, size / 2, (n, 2))
    z = 8 * np.sin(xy[:, 0] / 23.0) * np.cos(xy[:, 1] / 17.0) + 5 * np.exp(-(xy**2).sum(1) / 2000.0)
    return np.c_[xy, z]


def test_icp_point_to_plane_recovers_a_small_transform():
    rng = np.random.default_rng(0)
    target = bumpy_surface(rng)
    source_true = bumpy_surface(rng)                       # independent sampling of the same surface
    T = from_rotvec([0.8, -0.5, 0.3], np.radians([0.3, -0.2, 0.4]))
    source = (source_true - T[:3, 3]) @ T[:3, :3]          # = inv(T) applied
    res = icp_point_to_plane(source, target, max_distance_mm=3.0)
    dt, dr = pose_error(res.transformation, T)
    assert dt < 0.02 and np.degrees(dr) < 0.005
    assert res.fitness > 0.95 and res.rmse_mm < 0.3 and res.inliers > 5000
    with pytest.raises(RefineError):
        icp_point_to_plane(source[:, :2], target)


def test_point_to_plane_information_of_a_plane_leaves_sliding_free():
    rng = np.random.default_rng(1)
    P = np.c_[rng.uniform(-50, 50, (500, 2)), np.zeros(500)]
    N = np.tile([0, 0, 1.0], (500, 1))
    info = point_to_plane_information(P, N, P.mean(0), sigma_mm=0.1, effective_points=100)
    w = np.linalg.eigvalsh(info)
    # a plane fixes z, rx, ry; x, y and rz are free
    assert np.sum(w < 1e-9 * w.max()) == 3
    assert info[2, 2] == pytest.approx(100 / 0.01)


TRANSFER_COV = np.diag([0.3**2] * 3 + [np.radians(0.05) ** 2] * 3)


def _strip(n_scans: int = 12, per_station: int = 3, seed: int = 2):
    """True scan poses along x, tracker priors with a random-walk error per transfer plus reading noise;
    returns the truth, the priors, the transfers' priors and the generator."""
    rng = np.random.default_rng(seed)
    truth = [from_rotvec([250.0 * i, 0, 500.0], [0, np.pi, 0.02 * i]) for i in range(n_scans)]
    station = [i // per_station for i in range(n_scans)]
    drift, transfers = [np.eye(4)], []
    for k in range(1, max(station) + 1):                  # each transfer about the target, at its first scan
        c = np.array([250.0 * per_station * k, 0, 500.0])
        step = from_rotvec(rng.normal(0, 0.3, 3), rng.normal(0, np.radians(0.05), 3))
        drift.append(from_rotvec(c, [0, 0, 0]) @ step @ from_rotvec(-c, [0, 0, 0]) @ drift[-1])
        transfers.append(TransferPrior(k, c, TRANSFER_COV))
    sig_t, sig_r = 0.02, np.radians(0.002)
    cov = np.diag([sig_t**2] * 3 + [sig_r**2] * 3)
    priors = []
    for X, k in zip(truth, station, strict=True):
        noise = from_rotvec(rng.normal(0, sig_t, 3), rng.normal(0, sig_r, 3))
        priors.append(ScanPrior(compose(drift[k], X, noise), cov, k))
    return truth, priors, transfers, rng


def _edges(truth, priors, rng, pairs, noise_mm=0.005, noise_rad=8.7e-6):
    edges = []
    info = np.diag([1 / noise_mm**2] * 3 + [1 / noise_rad**2] * 3)
    for i, j in pairs:
        P_i, P_j = priors[i].T_W_S, priors[j].T_W_S
        C = P_i @ invert(truth[i]) @ truth[j] @ invert(P_j)
        centre = (P_i[:3, 3] + P_j[:3, 3]) / 2
        # noise about the overlap centre
        e = from_rotvec(rng.normal(0, noise_mm, 3), rng.normal(0, noise_rad, 3))
        C = from_rotvec(centre, [0, 0, 0]) @ e @ from_rotvec(-centre, [0, 0, 0]) @ C
        edges.append(PairEdge(i, j, C, info, centre))
    return edges


def test_pose_graph_removes_drift_accumulated_across_transfers():
    truth, priors, transfers, rng = _strip()
    n = len(truth)
    edges = _edges(truth, priors, rng, [(i, i + 1) for i in range(n - 1)])
    res = refine_poses(priors, edges, transfers)
    assert res.success and res.cost_after < res.cost_before
    before = np.array([pose_error(p.T_W_S, X) for p, X in zip(priors, truth, strict=True)])
    after = np.array([pose_error(T, X) for T, X in zip(res.poses, truth, strict=True)])
    drifted = np.array([p.station > 0 for p in priors])
    assert np.median(after[drifted, 0]) * 5 < np.median(before[drifted, 0])
    assert np.median(after[drifted, 1]) * 5 < np.median(before[drifted, 1])
    assert np.median(after[:, 0]) < 0.05
    assert set(res.station_corrections) == {1, 2, 3}


def test_pose_graph_without_edges_keeps_the_tracker_poses():
    truth, priors, _, _ = _strip(n_scans=4)
    res = refine_poses(priors, [])
    for T, p in zip(res.poses, priors, strict=True):
        np.testing.assert_allclose(T, p.T_W_S, atol=1e-9)
    assert refine_poses([], []).poses == []


def test_pose_graph_rejects_bad_edges_and_covariances():
    truth, priors, transfers, rng = _strip(n_scans=6)
    with pytest.raises(RefineError, match="does not join"):
        refine_poses(priors, [PairEdge(0, 0, np.eye(4), np.eye(6), np.zeros(3))])
    with pytest.raises(RefineError, match="one for each station after the first"):
        refine_poses(priors, [], [TransferPrior(0, np.zeros(3), TRANSFER_COV)])     # station 0 defines W
    with pytest.raises(RefineError, match="one for each station after the first"):
        refine_poses(priors, [], [transfers[0], transfers[0]])
    bad = [ScanPrior(priors[0].T_W_S, -np.eye(6), 0)]
    with pytest.raises(RefineError, match="positive definite"):
        refine_poses(bad, [])


def test_scan_covariance_carries_target_rotation_to_the_scan_origin():
    from tandemscan.pipeline.geometry.uncertainty import scan_pose_covariance

    reading = np.diag([0.01**2] * 3 + [1e-5**2] * 3)
    T_T_S = from_rotvec([0, 0, 100.0], [0, 0, 0])      # scanner 100 mm along the target's z
    C = scan_pose_covariance(np.eye(4), np.eye(4), T_T_S, reading)
    # x and y of the scan origin pick up (1e-5 rad * 100 mm)^2; z (along the lever) does not
    np.testing.assert_allclose(np.diag(C)[:3], [1e-4 + 1e-6, 1e-4 + 1e-6, 1e-4])
    np.testing.assert_allclose(np.diag(C)[3:], [1e-10] * 3)
    # a world frame turned 90 deg about z swaps the x and y axes of a non-isotropic covariance
    reading2 = np.diag([1.0, 4.0, 9.0, 1e-8, 1e-8, 1e-8])
    C2 = scan_pose_covariance(from_rotvec([0, 0, 0], [0, 0, np.pi / 2]), np.eye(4), np.eye(4), reading2)
    np.testing.assert_allclose(np.diag(C2)[:3], [4.0, 1.0, 9.0], atol=1e-12)


def test_transfer_covariance_adds_both_readings_in_world_axes():
    from tandemscan.pipeline.geometry.uncertainty import transfer_covariance

    before = np.diag([1.0, 4.0, 9.0, 1e-8, 2e-8, 3e-8])
    after = np.diag([0.5, 0.5, 0.5, 1e-8, 1e-8, 1e-8])
    turned = from_rotvec([5000.0, 0, 0], [0, 0, np.pi / 2])         # the new camera, turned 90 deg about z
    C = transfer_covariance(np.eye(4), before, turned, after)
    np.testing.assert_allclose(np.diag(C), [1.5, 4.5, 9.5, 2e-8, 3e-8, 4e-8], atol=1e-12)
    C2 = transfer_covariance(np.eye(4), after, turned, before)       # the second reading's x, y swap in W
    np.testing.assert_allclose(np.diag(C2), [4.5, 1.5, 9.5, 3e-8, 2e-8, 4e-8], atol=1e-12)


def test_covariance_about_another_centre_adds_the_rotation_lever():
    from tandemscan.pipeline.geometry.uncertainty import covariance_about

    rng = np.random.default_rng(4)
    C = np.diag([0.01, 0.02, 0.03, 1e-6, 2e-6, 3e-6])
    c, c2 = np.array([100.0, 0, 0]), np.array([100.0, 0, 1000.0])   # 1 m along z
    D = covariance_about(C, c, c2)
    # a rotation about x or y moves the new centre sideways by r * 1000 mm; about z it does not
    np.testing.assert_allclose(np.diag(D)[:3], [0.01 + 2e-6 * 1e6, 0.02 + 1e-6 * 1e6, 0.03])
    # the same by sampling motions about c and looking where they move c2
    x = rng.multivariate_normal(np.zeros(6), C, 20000)
    moved = np.array([from_rotvec(c, [0, 0, 0]) @ from_rotvec(t, r) @ from_rotvec(-c, [0, 0, 0]) @ np.r_[c2, 1]
                      for t, r in zip(x[:, :3], x[:, 3:], strict=True)])[:, :3] - c2
    S = np.cov(moved.T)
    np.testing.assert_allclose(np.diag(S), np.diag(D)[:3], rtol=0.05)
    np.testing.assert_allclose(S, D[:3, :3], atol=0.05)


def test_constrained_edge_drops_the_sliding_directions_of_a_plane():
    from tandemscan.pipeline.registration.pose_graph import constrained_edge

    rng = np.random.default_rng(3)
    P = np.c_[rng.uniform(-50, 50, (500, 2)), np.zeros(500)]
    info = point_to_plane_information(P, np.tile([0, 0, 1.0], (500, 1)), np.zeros(3), 0.05, 100)
    slide = from_rotvec([3.0, -2.0, 0.1], [0.001, -0.002, 0.05])   # mostly in-plane motion
    C, info_kept = constrained_edge(slide, info, np.zeros(3), 40.0, 0.01)
    # what a plane measures (z, rx, ry) is kept; the in-plane slide (x, y, rz) is gone
    t, r = C[:3, 3], Rotation.from_matrix(C[:3, :3]).as_rotvec()
    np.testing.assert_allclose([t[0], t[1], r[2]], 0.0, atol=1e-9)
    assert t[2] == pytest.approx(0.1, abs=1e-3) and r[0] == pytest.approx(0.001, rel=0.05)
    assert np.linalg.matrix_rank(info_kept, tol=1e-6 * np.abs(info_kept).max()) == 3


# ---------------------------------------------------------------- shared scanner-mount correction


def _relief(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return 10 * np.sin(x / 37.0) * np.cos(y / 29.0) + 6 * np.cos(x / 61.0 + y / 45.0)


def _mount_scans(D_true: np.ndarray, tilt_deg: float, seed: int = 5):
    """Nine scans of a relief on a 3x3 grid (100 mm apart, 130 mm radius: neighbours overlap), each from
    its own scanner orientation (tilts up to ``tilt_deg`` about x and y, any yaw), stitched through the
    tracker (reading noise) and a mount ``X_used`` off the true one: ``X_true = X_used D_true``."""
    from tandemscan.pipeline.geometry.frames import from_rpy, transform_points
    from tandemscan.pipeline.geometry.uncertainty import scan_pose_covariance
    from tandemscan.pipeline.registration.correction import StitchedScan

    rng = np.random.default_rng(seed)
    X_true = from_rpy([0.0, -90.0, 40.0], [np.pi, 0.0, 0.0])
    X_used = X_true @ invert(D_true)
    reading_cov = np.diag([0.01**2] * 3 + [np.radians(0.001) ** 2] * 3)
    truth, scans = [], []
    for cx, cy in ((x, y) for x in (-100.0, 0.0, 100.0) for y in (-100.0, 0.0, 100.0)):
        tilt = np.radians(rng.uniform(-tilt_deg, tilt_deg, 2)) if tilt_deg else np.zeros(2)
        yaw = rng.uniform(-np.pi, np.pi) if tilt_deg else 0.0
        R = (Rotation.from_euler("z", yaw) * Rotation.from_euler("xy", tilt) * Rotation.from_euler("x", np.pi))
        c = np.array([cx, cy, _relief(cx, cy)])
        T_W_S = from_rotvec(c - 442.0 * R.as_matrix()[:, 2], R.as_rotvec())     # looking along its +z
        xy = np.array([cx, cy]) + 130.0 * np.sqrt(rng.uniform(0, 1, 6000))[:, None] * np.c_[
            np.cos(a := rng.uniform(0, 2 * np.pi, 6000)), np.sin(a)]
        P_S = transform_points(invert(T_W_S), np.c_[xy, _relief(xy[:, 0], xy[:, 1])])
        P_S[:, 2] += rng.normal(0, 0.02, len(P_S))
        T_C_T = T_W_S @ invert(X_true)                                  # W = C: one tracker station
        noisy = from_rotvec(rng.normal(0, 0.01, 3), [0, 0, 0]) @ _turned(T_C_T, rng.normal(0, np.radians(0.001), 3))
        truth.append(T_W_S)
        cov = scan_pose_covariance(np.eye(4), noisy, X_used, reading_cov)
        scans.append(StitchedScan(P_S, noisy @ X_used, cov, 0))
    return truth, scans


def _turned(T: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    """``T`` turned about its own origin by a world-axes rotation vector (a tracker's orientation noise)."""
    out = T.copy()
    out[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix() @ T[:3, :3]
    return out


def _mount_run(D_true: np.ndarray, tilt_deg: float, prior_sigma=(0.3, 8.7e-4)):
    """Correct the scans with and without the mount unknown (prior 1-sigma mm, rad per axis)."""
    from tandemscan.config.models import CorrectionConfig
    from tandemscan.pipeline.registration.correction import CorrectionSettings, StitchedJob, correct_scans
    from tandemscan.pipeline.registration.mount_unknown import MountPrior

    truth, scans = _mount_scans(D_true, tilt_deg)
    cfg = CorrectionSettings.from_section(CorrectionConfig(method="icp", min_overlap_points=100))
    prior = MountPrior(np.diag([prior_sigma[0] ** 2] * 3 + [prior_sigma[1] ** 2] * 3))
    with_mount = correct_scans(StitchedJob(scans, mount_prior=prior), cfg)
    without = correct_scans(StitchedJob(scans), cfg)

    def errors(poses):
        return np.array([pose_error(T, X)[0] for T, X in zip(poses, truth, strict=True)])

    return with_mount, errors(with_mount.poses), errors(without.poses), errors([s.T_W_S for s in scans])


def test_pose_graph_recovers_a_scanner_mount_error_from_overlaps_at_different_orientations():
    D = from_rotvec([0.25, -0.15, 0.2], np.radians([0.02, -0.03, 0.025]))
    res, after, without, before = _mount_run(D, tilt_deg=25.0)
    dt, dr = pose_error(res.mount.correction, D)
    assert dt < 0.05 and np.degrees(dr) < 0.005                       # from 0.36 mm and 0.043 deg
    assert np.median(after) * 3 < np.median(without) < np.median(before)
    # the posterior is tighter than the prior in every axis, and it covers the error
    sig = np.sqrt(np.diag(res.mount.covariance))
    assert np.all(sig < np.sqrt(np.diag(res.mount.prior_covariance)))
    assert dt < 4 * np.linalg.norm(sig[:3])
    assert res.mount.estimated == 6 and np.all(res.mount.information_ratio > 1.0)


def test_pose_graph_leaves_a_correct_scanner_mount_alone():
    res, after, without, _ = _mount_run(np.eye(4), tilt_deg=25.0)
    dt, dr = pose_error(res.mount.correction, np.eye(4))
    assert dt < 0.03 and np.degrees(dr) < 0.003                       # prior: 0.3 mm, 0.05 deg per axis
    # what it finds is the estimate's own noise: within its posterior (chi-square, 6 DoF, 99.9 %) ...
    d = np.r_[res.mount.correction[:3, 3], Rotation.from_matrix(res.mount.correction[:3, :3]).as_rotvec()]
    assert d @ np.linalg.solve(res.mount.covariance, d) < 22.5
    # ... and that is all it adds to the poses
    sigma_t = np.linalg.norm(np.sqrt(np.diag(res.mount.covariance))[:3])
    assert np.median(after) <= np.median(without) + 2 * sigma_t


def test_scanner_mount_translation_is_unobservable_when_every_scan_has_the_same_orientation():
    # relative poses between scans of one orientation are translations, which a mount translation
    # leaves unchanged (D^-1 Tr(u) D = Tr(R_D^T u)): the data say nothing about it and the prior holds it
    D = from_rotvec([0.25, -0.15, 0.2], [0, 0, 0])
    res, *_ = _mount_run(D, tilt_deg=0.0)
    w, V = np.linalg.eigh(res.mount.data_information)
    weak = w < 1e-6 * w.max()
    assert weak.sum() == 3
    np.testing.assert_allclose(np.linalg.norm(V[:3, weak], axis=0), 1.0, atol=1e-3)    # translations
    assert res.mount.estimated == 3 and np.sum(res.mount.information_ratio < 1.0) == 3
    assert np.linalg.norm(res.mount.correction[:3, 3]) < 1e-3                # held at the prior: 0
    np.testing.assert_allclose(np.sqrt(np.diag(res.mount.covariance)[:3]), 0.3, rtol=0.05)


def test_graph_jacobian_matches_finite_differences_of_the_residuals():
    """The Jacobian the solve uses (scans, transfers and a shared mount), at the tracker poses, against central
    differences of the exact residuals: it is exact there (first order only in the corrections themselves),
    so any wrong or missing block, or a term of the edges' own corrections left out, fails."""
    from tandemscan.pipeline.registration.pose_graph import _Graph

    truth, priors, transfers, rng = _strip(n_scans=9)
    edges = _edges(truth, priors, rng, [(i, i + 1) for i in range(8)] + [(0, 4), (2, 7)])
    graph = _Graph(priors, edges, transfers)
    graph.B = np.linalg.cholesky(np.diag([0.5**2] * 3 + [np.radians(0.1) ** 2] * 3))
    J = graph.jacobian(np.zeros(graph.n_blocks + 6)).toarray()
    x0 = np.zeros(J.shape[1])
    numeric = np.empty_like(J)
    for c in range(len(x0)):
        h = np.zeros_like(x0)
        h[c] = 1e-6
        numeric[:, c] = (graph.residuals(x0 + h) - graph.residuals(x0 - h)) / 2e-6
    scale = np.abs(numeric).max(axis=0)
    assert np.all(np.abs(J - numeric).max(axis=0) <= 1e-3 * scale + 1e-6)
    assert J.shape == (6 * 9 + 6 * len(transfers) + 6 * len(edges) + 6, 6 * (9 + len(transfers)) + 6)
