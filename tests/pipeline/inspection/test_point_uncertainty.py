"""Per-point expanded uncertainty along the CAD normal (pipeline/inspection/point_uncertainty.py) and the joint
covariance of the scans' pose errors it is propagated from (pipeline/registration/pose_covariance.py)."""

import numpy as np
import pytest
from tandemscan.pipeline.geometry.frames import from_rotvec, transform_points
from tandemscan.pipeline.inspection.point_uncertainty import GivenUncertainty, JobUncertainty, ScanCover
from tandemscan.pipeline.registration.joint import chain_covariance
from tandemscan.pipeline.registration.mount_unknown import MountPrior
from tandemscan.pipeline.registration.pose_covariance import PoseCovariance
from tandemscan.pipeline.registration.pose_graph import ScanPrior, TransferPrior

NOISE = 0.05


def plate(rng, x0, x1, step=2.0):
    """Points of the plane z = 0 over x0..x1 by 0..300 mm (F = W), normals +z."""
    x, y = np.meshgrid(np.arange(x0, x1, step), np.arange(0.0, 300.0, step))
    p = np.c_[x.ravel(), y.ravel(), np.zeros(x.size)]
    return p, np.tile([0.0, 0.0, 1.0], (len(p), 1))


def two_scans(sigma_t, sigma_r):
    """Two scans 450 mm above the plate, over x 0..300 and 250..550 mm, independent pose errors."""
    origins = np.array([[150.0, 150.0, 450.0], [400.0, 150.0, 450.0]])
    C = np.diag(([sigma_t**2] * 3 + [sigma_r**2] * 3) * 2)
    return PoseCovariance(np.arange(2), origins, np.eye(12), C, "test")


def model(rng, poses, counts=None):
    pa, _ = plate(rng, 0.0, 300.0)
    pb, _ = plate(rng, 250.0, 550.0)
    cover = ScanCover([pa, pb], np.array([len(pa), len(pb)], float), poses.origins_mm, np.arange(2))
    return JobUncertainty(poses, cover, NOISE, counts)


def test_translation_along_the_normal_is_counted_without_alignment_and_absorbed_by_a_best_fit():
    rng = np.random.default_rng(1)
    p, n = plate(rng, 0.0, 550.0)
    poses = two_scans(0.1, 0.0)
    m = model(rng, poses)
    u = m.evaluate(p, n, 2.0, np.eye(4), "none", None, None)
    # one scan's points: t_z of 0.1 mm and the noise along a ray at most 35 deg off the normal
    single = p[:, 0] < 200.0
    assert np.all(u.expanded_mm[single] <= 2.0 * np.hypot(0.1, NOISE) + 1e-9)
    assert np.all(u.expanded_mm[single] >= 2.0 * np.hypot(0.1, NOISE * np.cos(np.radians(35.0))) - 1e-9)
    # the overlap averages the two scans' independent errors
    both = (p[:, 0] > 270.0) & (p[:, 0] < 280.0)
    assert np.median(u.expanded_mm[both]) < np.median(u.expanded_mm[single])
    assert set(u.budget_mm) == {"scan_poses", "installation", "scanner_noise", "alignment"}
    assert u.budget_mm["scan_poses"] == pytest.approx(0.2, rel=0.05) and u.budget_mm["alignment"] == 0.0
    fitted = m.evaluate(p, n, 2.0, np.eye(4), "best-fit", None, None)
    # a best fit takes out the common shift: what is left is the two scans' difference, smaller everywhere
    assert np.median(fitted.expanded_mm) < 0.8 * np.median(u.expanded_mm)


def test_first_order_u_agrees_with_monte_carlo_of_the_best_fit():
    """GUM S1 in small: draw the scans' pose errors and noise, move the points, best-fit the plane (three dof
    of the plate: z, tilts), and compare each point's 2-sigma of the fitted deviation with the first-order U."""
    rng = np.random.default_rng(2)
    pa, na = plate(rng, 0.0, 300.0, 6.0)
    pb, nb = plate(rng, 250.0, 550.0, 6.0)
    p = np.r_[pa, pb]
    n = np.r_[na, nb]
    scan = np.r_[np.zeros(len(pa), int), np.ones(len(pb), int)]
    poses = two_scans(0.08, 2e-4)
    m = JobUncertainty(poses, ScanCover([pa, pb], np.array([len(pa), len(pb)], float), poses.origins_mm,
                                        np.arange(2)), NOISE, None)
    first = m.evaluate(p, n, 2.0, np.eye(4), "best-fit", None, None).expanded_mm
    draws = []
    L = np.linalg.cholesky(poses.theta_covariance)
    for _ in range(400):
        e = (L @ rng.standard_normal(12)).reshape(2, 6)
        q = np.empty_like(p)
        for i in range(2):
            o = poses.origins_mm[i]
            T = from_rotvec(o, [0, 0, 0]) @ from_rotvec(e[i, :3], e[i, 3:]) @ from_rotvec(-o, [0, 0, 0])
            q[scan == i] = transform_points(T, p[scan == i])
        rays = q - poses.origins_mm[scan]
        q += rays / np.linalg.norm(rays, axis=1, keepdims=True) * rng.normal(0.0, NOISE, (len(q), 1))
        d = q[:, 2]
        # the best fit of a plane to CAD z = 0 (z, rotations about x and y) about the centroid
        c = p.mean(axis=0)
        J = np.c_[np.ones(len(p)), (p[:, 1] - c[1]), -(p[:, 0] - c[0])]
        a, *_ = np.linalg.lstsq(J, -d, rcond=None)
        draws.append(d + J @ a)
    mc = 2.0 * np.std(draws, axis=0)
    alone = (p[:, 0] < 250.0) | (p[:, 0] >= 300.0)  # the model averages the overlap's two scans, the draws do not
    ratio = first[alone] / mc[alone]
    assert np.median(ratio) == pytest.approx(1.0, abs=0.1)
    assert np.percentile(ratio, 5) > 0.8 and np.percentile(ratio, 95) < 1.2


def test_the_voxel_count_divides_the_noise_and_given_uncertainties_add_nothing_but_the_alignment():
    rng = np.random.default_rng(3)
    p, n = plate(rng, 0.0, 200.0)
    poses = two_scans(0.0, 0.0)
    one = model(rng, poses).evaluate(p, n, 2.0, np.eye(4), "none", None, None)
    four = model(rng, poses, np.full(len(p), 4)).evaluate(p, n, 2.0, np.eye(4), "none", None, None)
    np.testing.assert_allclose(four.expanded_mm, one.expanded_mm / 2.0, rtol=1e-9)
    np.testing.assert_allclose(one.noise_variance_mm2, (one.expanded_mm / 2.0) ** 2, rtol=1e-9)
    given = GivenUncertainty(0.3, k=3.0).evaluate(p, n, 2.0, np.eye(4), "best-fit", None, None)
    np.testing.assert_allclose(given.expanded_mm, 0.2)  # 0.3 at k = 3 is 0.2 at k = 2
    per_point = np.linspace(0.1, 0.2, len(p))
    kept = np.arange(len(p)) % 2 == 0
    given = GivenUncertainty(per_point).evaluate(p[kept], n[kept], 2.0, np.eye(4), "none", kept, None)
    np.testing.assert_allclose(given.expanded_mm, per_point[kept])


def test_the_chain_covariance_carries_transfers_and_the_mount_to_every_scan_and_the_prior_replaces_the_mount():
    T0 = np.eye(4)
    T1 = from_rotvec([500.0, 0, 0], [0, 0, 0])
    tight = np.diag([0.01] * 3 + [1e-8] * 3)
    priors = [ScanPrior(T0, tight, 0), ScanPrior(T1, tight, 1)]
    transfer = TransferPrior(1, np.array([250.0, 0, 0]), np.diag([0.25] * 3 + [1e-8] * 3))
    mount = MountPrior(np.diag([4.0] * 3 + [1e-6] * 3))
    cov = chain_covariance(priors, [transfer], mount)
    full = cov.full()
    assert cov.source == "tracker chain prior" and len(cov.installation_columns) == 6
    # scan 0: its reading and the mount; scan 1 also the transfer; the mount correlates them
    np.testing.assert_allclose(np.diag(full)[:3], 0.01 + 4.0, rtol=1e-9)
    np.testing.assert_allclose(np.diag(full)[6:9], 0.01 + 0.25 + 4.0, rtol=1e-3)  # + the lever of its tilt
    np.testing.assert_allclose(full[0, 6], 4.0, rtol=1e-9)
    G = cov.factor("installation")
    np.testing.assert_allclose((G @ G.T)[0, 0], 4.0, rtol=1e-9)
    shrunk = PoseCovariance(cov.scan_ids, cov.origins_mm, cov.A, cov.theta_covariance * 1e-4, cov.source,
                            cov.installation_columns)
    back = shrunk.with_installation_at_prior().factor("installation")
    np.testing.assert_allclose((back @ back.T)[0, 0], 4.0, rtol=1e-9)
    with pytest.raises(ValueError, match="do not fit"):
        PoseCovariance(np.arange(3), cov.origins_mm, cov.A, cov.theta_covariance, "bad")


def test_the_pose_variance_from_covariance_blocks_is_that_of_the_factor():
    """Three scans on two tracker stations with a transfer and the mount (correlated errors), their covers
    overlapping: each point's pose variance from the 6x6 blocks of ``PoseCovariance.covariance`` equals
    ``|G^T v|^2`` with the factor ``G`` of each part and ``v`` the point's gradients over all scans, less the best
    fit's absorption (to the rounding of the sums, 1e-9 relative)."""
    rng = np.random.default_rng(5)
    poses_W = [np.eye(4), from_rotvec([200.0, 0, 0], [0, 0.01, 0]), from_rotvec([400.0, 0, 0], [0.01, 0, 0])]
    tight = np.diag([0.01] * 3 + [1e-8] * 3)
    priors = [ScanPrior(T, tight, k // 2) for k, T in enumerate(poses_W)]
    cov = chain_covariance(priors, [TransferPrior(1, np.array([300.0, 0, 0]), np.diag([0.25] * 3 + [1e-7] * 3))],
                           MountPrior(np.diag([4.0] * 3 + [1e-6] * 3)))
    p, n = plate(rng, 0.0, 550.0, step=10.0)
    covers = [plate(rng, x0, x0 + 250.0)[0] for x0 in (0.0, 150.0, 300.0)]
    cover = ScanCover(covers, np.array([len(c) for c in covers], float), cov.origins_mm, np.arange(3))
    m = JobUncertainty(cov, cover, NOISE)
    at = cover.shares(p)
    absorb = m._absorption(p, n, p, n, at)
    for part in ("all", "scan_poses", "installation"):
        G = cov.factor(part)
        rows, g = m._gradients(p, n, at)
        v = np.zeros((len(p), G.shape[0]))
        for k in range(rows.shape[1]):
            np.add.at(v, (np.arange(len(p))[:, None], 6 * rows[:, k, None] + np.arange(6)), g[:, k])
        for fit in (None, absorb):
            w = v if fit is None else v - np.hstack([n, np.cross(p - fit[1], n)]) @ fit[0]
            want = np.einsum("mr,mr->m", w @ G, w @ G)
            got = m._pose_variance(cov.covariance(part), p, n, p, n, at, fit)
            np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12 * want.max())
            assert want.max() > 0
