"""DeepMerge network: shapes, the SVD head on perfect correspondences, the reflection fix, gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from tandemscan.pipeline.deepmerge.model import DeepMerge, PointFeatureExtractor, rigid_errors, weighted_procrustes


def _rt(seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    rng = np.random.default_rng(seed)
    R = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    return torch.tensor(R), torch.tensor(rng.normal(size=3) * 5.0)


def test_extractor_maps_k_by_14_structures_to_512_per_point():
    x = torch.randn(2, 37, 10, 14)
    f = PointFeatureExtractor()(x)
    assert f.shape == (2, 37, 512)
    widths = [m[0].out_channels for m in PointFeatureExtractor().local] + [512]
    assert widths == [64, 64, 128, 256, 512]
    with pytest.raises(ValueError):
        PointFeatureExtractor(widths=(64, 64, 128))


def test_svd_head_recovers_an_exact_transform_from_perfect_correspondences():
    torch.manual_seed(0)
    src = torch.randn(3, 50, 3, dtype=torch.float64)
    Rs, ts = zip(*(_rt(s) for s in range(3)), strict=True)
    R_true, t_true = torch.stack(Rs), torch.stack(ts)
    tgt = src @ R_true.transpose(1, 2) + t_true[:, None]
    w = torch.rand(3, 50, dtype=torch.float64) + 0.1
    R, t = weighted_procrustes(src, tgt, w)
    torch.testing.assert_close(R, R_true, atol=1e-10, rtol=0)
    torch.testing.assert_close(t, t_true, atol=1e-10, rtol=0)


def test_svd_head_weights_select_the_inliers():
    torch.manual_seed(1)
    src = torch.randn(1, 40, 3, dtype=torch.float64)
    R_true, t_true = _rt(5)
    tgt = src @ R_true.T + t_true
    tgt[:, :10] += 3.0 * torch.randn(1, 10, 3, dtype=torch.float64)      # outliers
    w = torch.ones(1, 40, dtype=torch.float64)
    w[:, :10] = 0.0
    R, t = weighted_procrustes(src, tgt, w)
    torch.testing.assert_close(R[0], R_true, atol=1e-10, rtol=0)


def test_svd_head_never_returns_a_reflection():
    torch.manual_seed(2)
    src = torch.randn(1, 30, 3, dtype=torch.float64)
    mirror = torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64))
    R, _ = weighted_procrustes(src, src @ mirror, torch.ones(1, 30, dtype=torch.float64))
    assert torch.linalg.det(R).item() == pytest.approx(1.0)
    torch.testing.assert_close(R[0] @ R[0].T, torch.eye(3, dtype=torch.float64), atol=1e-12, rtol=0)


def test_network_returns_one_rigid_estimate_per_iteration_and_gradients_reach_every_layer():
    torch.manual_seed(3)
    net = DeepMerge(iterations=3)
    xyz = torch.randn(2, 64, 3)
    struct = torch.randn(2, 64, 10, 14)
    outs = net(struct, struct + 0.01, xyz, xyz + 0.01)
    assert len(outs) == 3
    for R, t in outs:
        assert R.shape == (2, 3, 3) and t.shape == (2, 3)
        torch.testing.assert_close(R @ R.transpose(1, 2), torch.eye(3).expand(2, 3, 3), atol=1e-5, rtol=0)
    loss = sum(rigid_errors(R, t, torch.eye(3).expand(2, 3, 3), torch.full((2, 3), 0.01)).mean() for R, t in outs)
    loss.backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, f"no gradient reaches {name}"


def _wavy_pair(
    seed: int, rotvec_deg: list[float], t: list[float], points: int
) -> tuple[list[torch.Tensor], np.ndarray]:
    """Network inputs of two disjoint samplings of a wavy unit-size surface, the source turned by
    ``rotvec_deg`` and moved by ``t``; returns the inputs and the source's rotation error."""
    from tandemscan.pipeline.deepmerge.features import reference_direction
    from tandemscan.pipeline.deepmerge.register import prepare_cloud

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-1.0, 1.0, (8000, 2))
    P = np.c_[xy, 0.3 * np.sin(2.5 * xy[:, 0]) * np.cos(2.0 * xy[:, 1])]
    R_err = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    ref = reference_direction(P[1::2])
    s_st, s_xyz = prepare_cloud(P[::2] @ R_err.T + t, points, 10, 0.04, ref, rng)
    t_st, t_xyz = prepare_cloud(P[1::2], points, 10, 0.04, ref, rng)
    return [torch.from_numpy(a)[None] for a in (s_st, t_st, s_xyz, t_xyz)], R_err


def test_the_untrained_head_is_a_soft_nearest_neighbour_registration_that_iterations_sharpen():
    """With the distance term in residual units, more head iterations keep improving a small error."""
    args, R_err = _wavy_pair(4, [1.5, -1.0, 2.0], [0.02, -0.01, 0.015], 512)
    net = DeepMerge(iterations=3).eval()
    errors = []
    with torch.no_grad():
        for R, _t in net(*args, iterations=8):
            # the truth maps src back: R_true = R_err^T, t_true = -R_err^T t_err
            M = R[0].double().numpy() @ R_err
            errors.append(np.degrees(Rotation.from_matrix(M).magnitude()))
    before = np.degrees(Rotation.from_matrix(R_err).magnitude())
    assert errors[0] < before and np.all(np.diff(errors) < 0)
    assert errors[-1] < 0.5 * before


@pytest.mark.slow
def test_inference_schedule_with_cheap_coarse_iterations_beats_the_fine_iterations_alone():
    args, R_err = _wavy_pair(5, [1.0, -1.5, 1.5], [0.0, 0.0, 0.0], 1024)
    net = DeepMerge(iterations=3).eval()
    with torch.no_grad():
        R_fine, _ = net.infer(*args, iterations=2)
        R_sched, _ = net.infer(*args, iterations=2, coarse_iterations=24, coarse_points=256)
    err = [np.degrees(Rotation.from_matrix(R[0].double().numpy() @ R_err).magnitude()) for R in (R_fine, R_sched)]
    assert err[1] < 0.5 * err[0]
