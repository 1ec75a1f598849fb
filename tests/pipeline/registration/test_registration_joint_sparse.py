"""The joint refinement's sparse paths against their dense formulas (docs/correction.md, "Joint refinement"): each
scan's posterior block, the mount's marginal information and ``PoseCovariance``'s blocks and products from the sparse
error model ``A`` and the sparse normal and information matrices; a job of 1,500 scans keeps that model and the
prior's blocks sparse-sized; the association's shortcuts (the target's box from its KD-tree, a pair's move told on
a subsample, a search again from the last one's two nearest neighbours) find what the full search finds."""

from __future__ import annotations

import dataclasses
import tracemalloc

import numpy as np
import pytest
from scipy import sparse
from scipy.spatial import cKDTree
from tandemscan.pipeline.compute import LocalBackend
from tandemscan.pipeline.geometry.frames import from_rotvec, invert, transform_points
from tandemscan.pipeline.registration import joint as joint_module
from tandemscan.pipeline.registration.joint import (
    JointScan,
    JointSettings,
    _covered,
    _marginal_information,
    _Match,
    _Model,
    _moved_beyond,
    _nearest,
    _nearest_again,
    _Pair,
    _PairWork,
    _scales,
    associate,
    joint_tree,
    refine_jointly,
)
from tandemscan.pipeline.registration.mount_unknown import MountPrior
from tandemscan.pipeline.registration.pose_covariance import PoseCovariance
from tandemscan.pipeline.registration.pose_graph import ScanPrior, TransferPrior

LOOSE = np.diag([0.3**2] * 3 + [np.radians(0.05) ** 2] * 3)


def strip(n: int, seed: int) -> tuple[list[JointScan], list[ScanPrior], list[tuple[int, int]], list[TransferPrior]]:
    """``n`` noisy scans (0.03 mm) of a curved strip, 150 mm windows 75 mm apart, two tracker stations."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(0.0, 75.0 * (n + 1) + 1, 3.0), np.arange(-60.0, 61.0, 3.0))
    x, y = x.ravel(), y.ravel()
    world = np.c_[x, y, 10 * np.sin(x / 17.0) * np.cos(y / 13.0) + 6 * np.cos(x / 23.0 + y / 19.0)]
    scans, priors = [], []
    for k in range(n):
        T = from_rotvec([75.0 * k + 75.0, 0.0, 400.0], [np.pi, 0, 0])
        inside = (world[:, 0] >= 75.0 * k) & (world[:, 0] <= 75.0 * k + 150.0)
        P = transform_points(invert(T), world[inside])
        P[:, 2] += rng.normal(0, 0.03, len(P))
        scans.append(JointScan.from_points(P))
        tracker = from_rotvec(rng.normal(0, 0.1, 3), rng.normal(0, 1e-4, 3)) @ T
        priors.append(ScanPrior(tracker, LOOSE, int(k >= n // 2)))
    transfers = [TransferPrior(1, np.array([75.0 * n / 2, 0, 400.0]), LOOSE)]
    return scans, priors, [(k, k + 1) for k in range(n - 1)], transfers


def test_the_sparse_posterior_blocks_equal_the_dense_products():
    """Each scan's posterior, ``PoseCovariance``'s blocks (the scans' own, the pairs asked for beyond the normal
    matrix's pattern, the shared unknowns'), a point's variance from every part's, its products and its ``theta``
    sub-blocks equal ``A C A^T`` with ``C = H^-1 I H^-1`` formed densely (1e-9 of the entries' scale, the two routes'
    rounding), the mount's marginal information the dense Schur complement."""
    scans, priors, pairs, transfers = strip(8, 1)
    mount = MountPrior(np.diag([0.01] * 3 + [1e-6] * 3))
    res = refine_jointly(scans, priors, pairs, [p.T_W_S for p in priors], transfers, mount,
                         JointSettings(iterations=2, reassociate_mm=0.02))
    pc = res.pose_covariance
    assert sparse.isspmatrix_csr(pc.A) and sparse.issparse(pc.normal) and sparse.issparse(pc.information)
    H_inv = np.linalg.inv(pc.normal.toarray())
    A, C = pc.A.toarray(), H_inv @ pc.information.toarray() @ H_inv
    n = len(scans)

    def close(got, want, sd_rows, sd_cols):
        """Entries within 1e-9 of sqrt(var_a var_b) (translations mm^2, rotations rad^2 each at their scale)."""
        scale = np.outer(sd_rows, sd_cols) + 1e-300
        assert np.all(np.abs(got - want) <= 1e-9 * scale), np.max(np.abs(got - want) / scale)

    full = A @ C @ A.T
    blocks = np.stack([full[6 * i:6 * i + 6, 6 * i:6 * i + 6] for i in range(n)])
    sd = np.sqrt(np.diag(full)).reshape(n, 6)
    for i in range(n):
        close(res.covariances[i], blocks[i], sd[i], sd[i])
    cols = np.r_[0:12, 6 * n:pc.normal.shape[0]]
    sd_theta = np.sqrt(np.diag(C))[cols]
    close(pc.theta_covariance(cols), C[np.ix_(cols, cols)], sd_theta, sd_theta)
    mount_cols = list(pc.installation_columns)
    assert len(mount_cols) == 6
    far = np.array([[0, n - 1], [1, n - 2]])           # no pair links them: outside the normal matrix's pattern
    for prior in (False, True):
        cov = pc.with_installation_at_prior() if prior else pc
        Cp = C.copy()
        if prior:
            Cp[mount_cols, :] = Cp[:, mount_cols] = 0.0
            Cp[mount_cols, mount_cols] = 1.0
        errors = cov.scan_errors(far)
        whole = A @ Cp @ A.T
        sd = np.sqrt(np.diag(whole)).reshape(n, 6)
        asked = np.r_[far, far[:, ::-1], np.c_[np.arange(n), np.arange(n)]]
        for i, k in asked:
            close(errors.covariance([i], [k])[0], whole[6 * i:6 * i + 6, 6 * k:6 * k + 6], sd[i], sd[k])
        # per part, a point's variance (ScanErrors.variances) over each pair asked for: 100 gradients (more than
        # the 78 coefficients of a quadratic form of the pair's 12 errors), scaled by the errors' sd
        rows = np.repeat(asked, 100, axis=0)
        g = np.random.default_rng(4).standard_normal((len(rows), 2, 6)) / sd[rows]
        got = errors.variances(rows, g)
        for part, keep in (("all", slice(None)), ("scan_poses", np.setdiff1d(np.arange(len(C)), mount_cols)),
                           ("installation", mount_cols)):
            Ck = np.zeros_like(Cp)
            Ck[np.ix_(np.arange(len(C))[keep], np.arange(len(C))[keep])] = Cp[np.ix_(np.arange(len(C))[keep],
                                                                                   np.arange(len(C))[keep])]
            want = A @ Ck @ A.T
            blocks = want.reshape(n, 6, n, 6).transpose(0, 2, 1, 3)[rows[:, :, None], rows[:, None, :]]
            dense = np.einsum("mkj,mkljq,mlq->m", g, blocks, g)
            scale = np.einsum("mkj,mkljq,mlq->m", np.abs(g), np.abs(blocks), np.abs(g))
            assert np.all(np.abs(got[part] - dense) <= 1e-9 * scale + 1e-300), part
            X = np.random.default_rng(2).standard_normal((6 * n, 6))
            got_X, dense_X = cov.times(X)[part], want @ X
            assert np.abs(got_X - dense_X).max() <= 1e-9 * np.abs(dense_X).max() + 1e-300
        with pytest.raises(KeyError):
            errors.covariance([0], [n // 2])   # not asked for

    M = sparse.random(60, 60, density=0.1, random_state=3)
    H = (M @ M.T + sparse.identity(60) * 5.0).tocsc()
    D = H.toarray()
    dense = D[54:, 54:] - D[:54, 54:].T @ np.linalg.solve(D[:54, :54], D[:54, 54:])
    assert np.abs(_marginal_information(H, 54) - dense).max() < 1e-12 * np.abs(dense).max()


def test_a_job_of_many_scans_keeps_its_error_model_sparse_sized():
    """1,500 scans, four stations and the mount (9,024 unknowns): the error model ``A`` and every scan's prior block
    are formed without any dense (6n x m) or (m x m) array: a dense ``A`` alone would be 650 MB, here the model's
    sparse matrices hold under 16 MB and the scans' prior blocks take under 64 MB traced."""
    n = 1500
    rng = np.random.default_rng(4)
    priors = [ScanPrior(from_rotvec(rng.uniform(-3000, 3000, 3), rng.normal(0, 1, 3)), LOOSE, k * 4 // n)
              for k in range(n)]
    transfers = [TransferPrior(s, rng.uniform(-3000, 3000, 3), LOOSE) for s in (1, 2, 3)]
    model = _Model(priors, transfers, MountPrior(np.diag([0.01] * 3 + [1e-6] * 3)))
    assert sparse.issparse(model.A) and model.A.shape == (6 * n, 6 * (n + 3 + 1))
    assert sparse.issparse(model.prior_covariance) and sparse.issparse(model.prior_information)
    stored = sum(M.data.nbytes + M.indices.nbytes + M.indptr.nbytes
                 for M in (model.A, model.prior_covariance, model.prior_information))
    assert stored < 16 * 2**20, stored / 2**20
    tracemalloc.start()
    blocks = model.scan_covariances(model.prior_covariance)    # each scan's columns found on the way
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert peak < 64 * 2**20, peak / 2**20
    # a scan of station 3: its reading's, three transfers' and the mount's prior through A, formed densely
    k = n - 1
    cols, Ak = model.scan_columns[k]
    assert len(cols) == 6 * (1 + 3 + 1)
    P = model.prior_covariance[cols][:, cols].toarray()
    assert np.allclose(blocks[k], Ak @ P @ Ak.T, rtol=1e-12, atol=0)
    assert np.all(np.linalg.eigvalsh(blocks[k]) > 0)
    given = PoseCovariance(np.arange(2), np.zeros((2, 3)), np.eye(12), np.eye(12), np.eye(12), "test")
    assert sparse.isspmatrix_csr(given.A)


def test_the_association_shortcuts_find_what_the_full_search_finds():
    """The target's box taken from its KD-tree and tested column by column leaves out no source point that has a
    target point within the distance (the search over all source points finds the same pairs); a pair's move
    beyond a limit is told the same from a subsample first as from all its points."""
    rng = np.random.default_rng(5)
    target = JointScan(rng.uniform(0, 100, (4000, 3)), np.tile([0.0, 0.0, 1.0], (4000, 1)))
    source = JointScan(rng.uniform(-20, 120, (5000, 3)), np.tile([0.0, 0.0, 1.0], (5000, 1)))
    rel = from_rotvec([3.0, -2.0, 1.0], [0.01, 0.02, -0.01])
    tree = joint_tree(target)
    found = associate(target, tree, source, rel, 3.0)
    d, idx = cKDTree(target.points_S).query(transform_points(rel, source.points_S), distance_upper_bound=3.0)
    every = np.flatnonzero(np.isfinite(d))
    assert len(every) > 300
    assert np.array_equal(found.source, every) and np.array_equal(found.target, idx[every])

    scans = [target, source]
    m = _Match(every, idx[every], np.zeros(len(every)), np.ones(len(every)), np.full(len(every), 2, np.uint16), rel)
    poses = np.stack([np.eye(4), rel])
    for rotation in (0.0, 1e-5, 4e-5, 1e-3):
        moved = poses.copy()
        moved[1] = from_rotvec([0, 0, 0], [0, 0, rotation]) @ rel
        shift = transform_points(invert(moved[0]) @ moved[1] - rel, source.points_S[every])
        farthest = float(np.sqrt(np.max(np.einsum("ij,ij->i", shift, shift))))
        for limit in (0.5 * farthest, farthest * (1 - 1e-9), farthest * 1.001, 0.002):
            assert _moved_beyond(scans, moved, _Pair(0, 1), m, limit) == (farthest > limit)


def test_a_search_again_from_the_last_one_finds_what_the_full_search_finds():
    """A pair searched again at poses moved a little (:func:`joint._nearest_again`, from the last search's two
    nearest neighbours and its near points) finds the same neighbours, in the same order, and places the same points
    (to the bit) as a full search there, for moves from well under the points' spacing to the search's reach (beyond
    it none: the pair is searched whole); a search made again names no reach, so the next one is a full one."""
    rng = np.random.default_rng(8)
    x, y = np.meshgrid(np.arange(0.0, 120.0, 2.0), np.arange(0.0, 80.0, 2.0))
    surface = np.c_[x.ravel(), y.ravel(), 5 * np.sin(x.ravel() / 11.0) * np.cos(y.ravel() / 7.0)]
    target = JointScan(surface + rng.normal(0, 0.3, surface.shape), np.tile([0.0, 0.0, 1.0], (len(surface), 1)))
    source = JointScan(surface[::-1] + rng.normal(0, 0.6, surface.shape), np.tile([0.0, 0.0, 1.0], (len(surface), 1)))
    tree = joint_tree(target)
    start = from_rotvec([0.4, -0.3, 0.2], [0.002, -0.001, 0.003])
    before, _ = _nearest(target, tree, source, start, 1.0)
    assert before.reach_mm == 1.25 and len(before.source) > 1000 and len(before.near) > 100
    assert np.all(before.gap_mm >= 0) and np.all((before.near_mm >= 1.0) & (before.near_mm < 1.25))
    for move_mm in (0.0, 0.01, 0.05, 0.1, 0.2, 0.4):
        moved = from_rotvec(move_mm * np.array([0.6, -0.48, 0.64]), [0.0, 0.0, move_mm / 2000]) @ start
        full, x_full = _nearest(target, tree, source, moved, 1.0)
        found = _nearest_again(target, tree, source, moved, 1.0, before, start)
        if move_mm > 0.2:     # beyond the reach's margin: to be searched whole
            assert found is None
            continue
        again, x_again = found
        assert np.array_equal(full.source, again.source) and np.array_equal(full.target, again.target)
        assert np.array_equal(x_full, x_again) and again.reach_mm == 0.0


def test_a_search_again_is_whole_where_points_neither_found_nor_near_moved_beyond_the_margin():
    """A pair turned about its found points (they move 0.03 mm) while points of the source beyond the search's reach,
    90 mm away, move 0.29 mm (more than the reach's margin of 0.25 mm) and come within the distance: the search again
    (:func:`joint._nearest_again`) does not answer from the found and near points alone (it would miss those), the
    full search finds them."""
    x, y = np.meshgrid(np.arange(0.0, 101.0), np.arange(0.0, 21.0))
    up = np.tile([0.0, 0.0, 1.0], (x.size, 1))
    target = JointScan(np.c_[x.ravel(), y.ravel(), np.zeros(x.size)], up)
    sx, sy = np.meshgrid(np.r_[0.0:10.0, 90.0:100.0], np.arange(0.0, 20.0))
    sx, sy = sx.ravel(), sy.ravel()
    source = JointScan(np.c_[sx, sy, np.where(sx < 50.0, 0.5, 1.26)], up[: sx.size])  # the far ones beyond 1.25 mm
    tree = joint_tree(target)
    before, _ = _nearest(target, tree, source, np.eye(4), 1.0)
    assert len(before.source) == 200 and len(before.near) == 0
    turned = from_rotvec([0.0, 0.0, 0.0], [0.0, 0.0032, 0.0])  # the far points 0.29 mm down, to 0.97 mm
    full, _ = _nearest(target, tree, source, turned, 1.0)
    assert len(full.source) == 400
    assert _nearest_again(target, tree, source, turned, 1.0, before, np.eye(4)) is None


def test_the_points_a_pair_covers_are_each_named_once_in_order():
    """A pair's covered target points (:func:`joint._covered`, counted by index) are ``np.unique`` of its matches'
    targets, the same dtype; none where it has none."""
    rng = np.random.default_rng(6)
    for count in (0, 1, 4500):
        targets = rng.integers(0, 26_000, count).astype(np.int32)
        m = _Match(np.arange(count, dtype=np.int32), targets, np.zeros(count), np.ones(count),
                   np.full(count, 2, np.uint16), np.eye(4))
        source, target = _covered(_Pair(0, 1), m)
        assert source is m.source and target.dtype == np.int32 and np.array_equal(target, np.unique(targets))


def test_the_normal_equations_find_the_normals_the_residuals_found():
    """The matches keep no normals (``_Match``: 26 bytes a correspondence): the normal equations find them again at
    the same poses, and they are those the residuals were found with, to the bit; the share follows the covering
    count (two scans or fewer: all of it)."""
    scans, priors, pairs, _ = strip(3, 4)
    poses = np.stack([s.T_W_S for s in priors])
    i, j = pairs[0]
    found = associate(scans[i], joint_tree(scans[i]), scans[j], invert(poses[i]) @ poses[j], 3.0)
    p = _Pair(i, j)
    m = _Match(found.source, found.target, np.zeros(len(found.source)), np.ones(len(found.source)),
               np.full(len(found.source), 2, np.uint16), np.eye(4))
    r, n = p.residuals(scans, poses, m)
    assert len(r) > 100 and np.abs(r).max() > 0
    m = p.at(scans, poses, m)
    assert np.array_equal(m.residual, r)
    origins = poses[:, :3, 3]
    weights = np.random.default_rng(1).uniform(0.5, 2.0, len(r))
    huber = np.where(np.arange(len(r)) % 7 == 0, 0.5, 1.0)
    given = p.normal_equations(scans, poses, origins, m, weights, huber, n)
    again = p.normal_equations(scans, poses, origins, m, weights, huber)
    assert all(np.array_equal(a, b) for a, b in zip(given, again, strict=True))
    assert np.abs(given[0]).max() > 0
    covering = np.array([1, 2, 3, 4], np.uint16)
    assert np.array_equal(dataclasses.replace(m, covering=covering).share, [1.0, 1.0, 2 / 3, 0.5])


def _scales_of(residuals: list[np.ndarray], variances: list[np.ndarray]) -> tuple[float, float, float]:
    """The RMS and robust scales of the residuals all together, as one array gives them."""
    r, v = np.concatenate(residuals), np.concatenate(variances)

    def robust(a: np.ndarray) -> float:
        return max(1.4826 * float(np.median(np.abs(a))), 1e-4) if len(a) else 1.0

    return float(np.sqrt(np.mean(r**2))), robust(r), robust(r / np.sqrt(v))


@pytest.mark.parametrize("fetch", [1 << 16, 3])
def test_the_residual_scales_found_where_the_matches_are_equal_those_of_all_residuals_together(monkeypatch, fetch):
    """The robust scales the refinement takes from its pairs' residuals on the backend, a few counts a round
    (``joint._scales``), are the medians of all residuals together to the bit: odd and even counts, ties, zeros
    and a bracket narrowed down to one float (``fetch`` 3: no values fetched)."""
    monkeypatch.setattr(joint_module, "_SCALE_FETCH", fetch)
    rng = np.random.default_rng(3)
    work = _PairWork(LocalBackend(1), [], "")
    for sizes in ([7], [4000, 1, 2999], [1000] * 70, [5, 6]):
        residuals = [rng.normal(0, 0.05, n) for n in sizes]
        if len(sizes) == 2:
            residuals[0][:3] = 0.0         # zeros at the median
        if len(sizes) == 3:
            residuals[2][:1500] = 0.0625   # a tie across the median
        variances = [rng.uniform(0.2, 1.0, n) for n in sizes]
        held = [(_Pair(0, 1), _Match(np.arange(n), np.arange(n), r, v, np.full(n, 2, np.uint16), np.eye(4)), n)
                for n, r, v in zip(sizes, residuals, variances, strict=True)]
        got = _scales(work, held)
        rms, sigma, whitened = _scales_of(residuals, variances)
        assert got.count == sum(sizes)
        assert (got.sigma_mm, got.whitened_sigma_mm) == (sigma, whitened), sizes
        assert got.rms_mm == pytest.approx(rms, rel=1e-14)
    empty = _scales(work, [])
    assert (empty.count, empty.sigma_mm, empty.whitened_sigma_mm) == (0, 1.0, 1.0) and np.isnan(empty.rms_mm)
