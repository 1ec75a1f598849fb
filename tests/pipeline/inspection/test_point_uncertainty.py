"""Per-point expanded uncertainty along the CAD normal (pipeline/inspection/point_uncertainty.py) and the joint
covariance of the scans' pose errors it is propagated from (pipeline/registration/pose_covariance.py)."""

import numpy as np
import pytest
from scipy.spatial import cKDTree
from tandemscan.pipeline.geometry.frames import from_rotvec, transform_points
from tandemscan.pipeline.inspection import point_uncertainty
from tandemscan.pipeline.inspection.point_uncertainty import (
    GivenUncertainty,
    JobUncertainty,
    ScanCover,
    _Absorbed,
    _covering_pairs,
)
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
    return PoseCovariance(np.arange(2), origins, np.eye(12), np.eye(12), C, "test")   # C = 1^-1 C 1^-1


def model(rng, poses, counts=None):
    pa, _ = plate(rng, 0.0, 300.0)
    pb, _ = plate(rng, 250.0, 550.0)
    cover = ScanCover([pa, pb], [np.eye(4)] * 2, np.array([len(pa), len(pb)], float), poses.origins_mm, np.arange(2))
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
    m = JobUncertainty(poses, ScanCover([pa, pb], [np.eye(4)] * 2, np.array([len(pa), len(pb)], float),
                                        poses.origins_mm, np.arange(2)), NOISE, None)
    first = m.evaluate(p, n, 2.0, np.eye(4), "best-fit", None, None).expanded_mm
    draws = []
    L = np.linalg.cholesky(poses.scan_covariances())   # (2, 6, 6): the two scans' errors are independent
    for _ in range(400):
        e = np.einsum("kij,kj->ki", L, rng.standard_normal((2, 6)))
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
    errors = cov.scan_errors(np.array([[0, 1]]))
    assert cov.source == "tracker chain prior" and len(cov.installation_columns) == 6
    # scan 0: its reading and the mount; scan 1 also the transfer; the mount correlates them
    np.testing.assert_allclose(np.diag(errors.covariance([0], [0])[0])[:3], 0.01 + 4.0, rtol=1e-9)
    np.testing.assert_allclose(np.diag(errors.covariance([1], [1])[0])[:3], 0.01 + 0.25 + 4.0, rtol=1e-3)  # + tilt
    np.testing.assert_allclose(errors.covariance([0], [1])[0][0, 0], 4.0, rtol=1e-9)
    along_x = np.array([[[1.0, 0, 0, 0, 0, 0]]])  # a point's gradient: scan 0's error along x

    def x_variances(c: PoseCovariance) -> dict[str, float]:
        """Per part, the variance (mm^2) of scan 0's error along x."""
        return {k: v[0] for k, v in c.scan_errors(np.zeros((0, 2))).variances(np.array([[0]]), along_x).items()}

    assert x_variances(cov)["installation"] == pytest.approx(4.0, rel=1e-9)
    assert x_variances(cov)["all"] == pytest.approx(0.01 + 4.0, rel=1e-9)
    shrunk = PoseCovariance(cov.scan_ids, cov.origins_mm, cov.A, cov.normal, cov.information * 1e-4, cov.source,
                            cov.installation_columns)
    back = shrunk.with_installation_at_prior()
    assert x_variances(back)["installation"] == pytest.approx(4.0, rel=1e-9)  # the mount at its prior, not shrunk
    assert x_variances(back)["scan_poses"] == pytest.approx(0.01e-4, rel=1e-6)
    np.testing.assert_allclose(back.scan_covariances()[0][0, 0], 0.01e-4 + 4.0, rtol=1e-9)
    with pytest.raises(ValueError, match="do not fit"):
        PoseCovariance(np.arange(3), cov.origins_mm, cov.A, cov.normal, cov.information, "bad")


def coupled(cov: PoseCovariance, links: list[tuple[int, int]], seed: int) -> PoseCovariance:
    """``cov``'s unknowns observed as a joint refinement's are: its prior's information ``P`` plus pairs' 12x12
    information in the linked scans' errors, ``H = P + A^T N A``, and the information its errors carry, the same
    pairs' weighted otherwise (``I = P + A^T N' A``), so that ``C = H^-1 I H^-1`` couples the scans."""
    rng = np.random.default_rng(seed)
    n = len(cov.scan_ids)
    N, N2 = np.zeros((6 * n, 6 * n)), np.zeros((6 * n, 6 * n))
    for i, k in links:
        idx = np.r_[6 * i:6 * i + 6, 6 * k:6 * k + 6]
        J = rng.standard_normal((30, 12)) * np.r_[[1.0] * 3 + [300.0] * 3, [1.0] * 3 + [300.0] * 3] * 20.0
        w = rng.uniform(0.5, 1.5, 30)
        N[np.ix_(idx, idx)] += J.T @ (w[:, None] * J)
        N2[np.ix_(idx, idx)] += J.T @ (w[:, None] ** 2 * J)
    A = cov.A.toarray()
    return PoseCovariance(cov.scan_ids, cov.origins_mm, cov.A, cov.normal + A.T @ N @ A,
                          cov.information + A.T @ N2 @ A, "test", cov.installation_columns)


@pytest.mark.parametrize("links", [[], [(0, 1), (1, 2)], [(0, 1)]])
def test_the_pose_variance_from_covariance_blocks_is_that_of_the_dense_route(links):
    """Three scans on two tracker stations with a transfer and the mount (correlated errors), their covers
    overlapping: each point's pose variance from the blocks of ``PoseCovariance.scan_errors`` (the tracker chain's
    prior, or a posterior whose pairs couple the scans: pairs of scans that share points but no pair are blocks
    beyond the normal matrix's pattern) equals the dense route's ``v^T A C A^T v``, ``C = H^-1 I H^-1`` formed
    whole, ``v`` the point's gradients over all scans, less the best fit's absorption (1e-9 relative); the mount at
    its prior likewise. The joint refinement's own blocks against the dense route: test_registration_joint_sparse."""
    rng = np.random.default_rng(5)
    poses_W = [np.eye(4), from_rotvec([200.0, 0, 0], [0, 0.01, 0]), from_rotvec([400.0, 0, 0], [0.01, 0, 0])]
    tight = np.diag([0.01] * 3 + [1e-8] * 3)
    priors = [ScanPrior(T, tight, k // 2) for k, T in enumerate(poses_W)]
    cov = coupled(chain_covariance(priors, [TransferPrior(1, np.array([300.0, 0, 0]),
                                                          np.diag([0.25] * 3 + [1e-7] * 3))],
                                   MountPrior(np.diag([4.0] * 3 + [1e-6] * 3))), links, 6)
    p, n = plate(rng, 0.0, 550.0, step=10.0)
    covers = [plate(rng, x0, x0 + 250.0)[0] for x0 in (0.0, 150.0, 300.0)]
    cover = ScanCover(covers, [np.eye(4)] * len(covers), np.array([len(c) for c in covers], float), cov.origins_mm,
                      np.arange(3))
    at = cover.shares(p)
    H_inv = np.linalg.inv(cov.normal.toarray())
    dense = H_inv @ cov.information.toarray() @ H_inv
    mount = list(cov.installation_columns)
    at_prior = dense.copy()
    at_prior[mount, :] = at_prior[:, mount] = 0.0
    at_prior[mount, mount] = 1.0
    for poses, C in ((cov, dense), (cov.with_installation_at_prior(), at_prior)):
        m = JobUncertainty(poses, cover, NOISE)
        absorb = m._absorption(p, n, p, n, at)
        rows, g = m._gradients(p, n, at)
        errors = poses.scan_errors(_covering_pairs(rows))
        for part in ("all", "scan_poses", "installation"):
            keep = np.isin(np.arange(len(C)), mount) if part == "installation" else (
                ~np.isin(np.arange(len(C)), mount) if part == "scan_poses" else np.ones(len(C), bool))
            A = poses.A.toarray()[:, keep]
            full = A @ C[np.ix_(keep, keep)] @ A.T
            v = np.zeros((len(p), full.shape[0]))
            for k in range(rows.shape[1]):
                np.add.at(v, (np.arange(len(p))[:, None], 6 * rows[:, k, None] + np.arange(6)), g[:, k])
            for fit in (None, absorb):
                w = v if fit is None else v - np.hstack([n, np.cross(p - fit[1], n)]) @ fit[0]
                want = np.einsum("mr,rs,ms->m", w, full, w)
                absorbed = None if fit is None else _Absorbed.of(poses, *fit)
                got = m._pose_variances(errors, p, n, p, n, at, absorbed)[part]
                # where the fit absorbs nearly all of a point's variance, the three terms' rounding (each 1e-13 of
                # itself, from the blocks and from the solves) is what is left: 1e-10 of the largest
                np.testing.assert_allclose(got, want, rtol=1e-9, atol=(1e-12 if fit is None else 1e-10) * want.max())
                assert want.max() > 0


def test_a_scan_cover_answers_by_slabs_as_one_tree_of_every_scan_and_holds_a_slab(monkeypatch):
    """:meth:`ScanCover.shares` a slab of x at a time gives the answer of one KD tree of every scan's points (each
    query's 16 nearest thinned points vote their scans, ``point_uncertainty`` module doc), with slabs far narrower
    than a scan, queries on slab edges and a sparse stretch whose nearest points lie beyond the first reach; the
    largest tree it builds holds the slab's points, a small share of the part's."""
    rng = np.random.default_rng(11)
    scans = [rng.uniform([60.0 * i, 0.0, 0.0], [60.0 * i + 150.0, 80.0, 2.0], (800, 3)) for i in range(24)]
    scans[5] = scans[5][::40]  # a sparse scan: its neighbours are far
    poses = [from_rotvec((5.0 + i, -2.0, 1.0), (0.001, -0.002, 0.0005 * (i % 3))) for i in range(24)]
    counts = rng.integers(2_000, 9_000, 24).astype(float)
    cover = ScanCover(scans, poses, counts, np.zeros((24, 3)), np.arange(24))
    queries = rng.uniform([0.0, 0.0, 0.0], [1500.0, 80.0, 2.0], (3000, 3))
    queries[:40, 0] = np.arange(40) * 20.0  # on the edges of 20 mm slabs
    built = []
    monkeypatch.setattr(point_uncertainty, "COVER_SLAB_MM", 20.0)
    monkeypatch.setattr(point_uncertainty, "COVER_REACH_MM", 2.0)
    monkeypatch.setattr(point_uncertainty, "cKDTree", lambda data, **kw: built.append(len(data)) or cKDTree(data, **kw))
    top, w = cover.shares(queries)

    placed = np.concatenate([transform_points(T, p) for T, p in zip(poses, scans, strict=True)])
    scan_of = np.repeat(np.arange(24), [len(p) for p in scans])
    near = scan_of[cKDTree(placed).query(queries, k=point_uncertainty.NEIGHBOURS)[1]]
    votes = np.zeros((len(queries), 24))
    np.add.at(votes, (np.repeat(np.arange(len(queries)), near.shape[1]), near.ravel()),
              (counts / [len(p) for p in scans])[near.ravel()])
    expected = np.argsort(-votes, axis=1)[:, :point_uncertainty.SCANS_PER_POINT]
    assert np.array_equal(top, expected)
    assert np.array_equal(w, (lambda v: v / v.sum(axis=1, keepdims=True))(np.take_along_axis(votes, expected, 1)))
    assert max(built) < len(placed) / 6 and len(built) > 40, max(built)
