"""DeepMerge training (smoke: a tiny model's loss falls), shipped weights, and the CLI commands."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from tandemscan.daemon.cli import main
from tandemscan.pipeline.deepmerge.register import DeepMergeRegistrar, RegistrationError, shipped_weights_path
from tandemscan.pipeline.deepmerge.train import TrainSettings, make_pool, perturb, train
from tandemscan.pipeline.geometry.frames import from_rotvec, invert, pose_error, transform_points
from tandemscan.pipeline.io.export import write_ply

TINY = TrainSettings(seed=3, train_pairs=6, val_pairs=2, shapes_per_pool=3, num_points=64, k=8,
                     widths=(8, 8, 16, 16, 32), batch_size=6, steps=50, lr=3e-3, use_part=False,
                     arbitrary_fraction=0.0, iterations=2, iterations_inference=3, iteration_weights=(0.5, 1.0),
                     val_points=64)


@pytest.mark.slow
def test_a_tiny_model_trains_and_its_loss_falls(tmp_path):
    torch.set_num_threads(1)
    out = tmp_path / "tiny.pt"
    _, summary = train(TINY, out)
    assert summary["steps"] == 50
    assert summary["loss_last_25"] < summary["loss_first_25"]
    val = summary["validation"]["trained_iterations"]
    assert {"tracker.rot_err_deg_median_after", "tracker.success_rate"} <= set(val)
    reg = DeepMergeRegistrar.load(out)
    assert reg.k == 8 and reg.model.extractor.last[0].out_channels == 32
    assert reg.iterations == TINY.iterations_inference


def test_a_run_cut_off_by_its_budget_leaves_a_checkpoint(tmp_path):
    torch.set_num_threads(1)
    out = tmp_path / "cut.pt"
    s = replace(TINY, steps=10_000, max_minutes=0.0, checkpoint_every=1)
    _, summary = train(s, out)
    assert summary["steps"] < 10_000 and summary["final"]
    assert torch.load(out, weights_only=True)["summary"]["steps"] == summary["steps"]


def test_pool_pairs_are_aligned_and_perturb_gives_the_inverse():
    pool = make_pool(2, 11, TINY)
    assert pool.src_struct.shape == (2, 64, 8, 14) and pool.tgt_xyz.shape == (2, 64, 3)
    R = torch.tensor(from_rotvec([0, 0, 0], [0.2, -0.1, 0.3])[:3, :3], dtype=torch.float32)[None]
    t = torch.tensor([[0.05, -0.02, 0.01]])
    xyz = torch.from_numpy(pool.src_xyz[:1])
    st, moved, R_true, t_true = perturb(torch.from_numpy(pool.src_struct[:1]), xyz, torch.from_numpy(pool.ref[:1]),
                                        R, t)
    back = moved @ R_true.transpose(1, 2) + t_true[:, None]
    torch.testing.assert_close(back, xyz, atol=1e-5, rtol=0)
    # distances (channels 6 and 13) do not change under a rigid motion
    torch.testing.assert_close(st[..., 6], torch.from_numpy(pool.src_struct[:1, ..., 6]))


def test_shipped_weights_load_and_register_two_clouds():
    reg = DeepMergeRegistrar.load(shipped_weights_path(), num_points=256)
    rng = np.random.default_rng(0)
    xy = rng.uniform(-60, 60, (3000, 2))
    P = np.c_[xy, 10 * np.sin(xy[:, 0] / 20) * np.cos(xy[:, 1] / 15)]
    T = reg.register(P[::2] + [0.5, 0, 0], P[1::2])
    assert T.shape == (4, 4) and np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-13, rtol=0)
    with pytest.raises(RegistrationError):
        DeepMergeRegistrar.load("/nonexistent/weights.pt")


def test_register_command_prints_the_transform_and_fitness(tmp_path, capsys):
    rng = np.random.default_rng(1)
    xy = rng.uniform(-80, 80, (8000, 2))
    P = np.c_[xy, 8 * np.sin(xy[:, 0] / 23) * np.cos(xy[:, 1] / 17) + 4 * np.cos(xy[:, 1] / 9)]
    T_true = from_rotvec([0.6, -0.4, 0.2], np.radians([0.2, -0.3, 0.25]))
    write_ply(tmp_path / "target.ply", P[1::2])
    write_ply(tmp_path / "source.ply", transform_points(invert(T_true), P[::2]))
    rc = main(["register", str(tmp_path / "source.ply"), str(tmp_path / "target.ply"), "--method", "icp",
               "--out", str(tmp_path / "T.txt")])
    assert rc == 0
    T = np.loadtxt(tmp_path / "T.txt")
    dt, dr = pose_error(T, T_true)
    assert dt < 0.05 and np.degrees(dr) < 0.01
    assert "fitness" in capsys.readouterr().out
    assert main(["register", str(tmp_path / "missing.ply"), str(tmp_path / "target.ply")]) == 2


@pytest.mark.slow
def test_re_embedding_rounds_bring_a_large_error_closer_than_one_pass():
    from tests.pipeline.registration.test_registration_stages import moved

    T_true = from_rotvec([4.0, -3.0, 2.0], np.radians([15.0, 10.0, -10.0]))      # 20.6 deg, 5.4 mm
    source, target = moved(T_true)
    one = pose_error(DeepMergeRegistrar.load(num_points=512, rounds=1).register(source, target), T_true)
    four = pose_error(DeepMergeRegistrar.load(num_points=512, rounds=4).register(source, target), T_true)
    assert np.degrees(four[1]) < 0.5 and np.degrees(four[1]) * 5 < np.degrees(one[1]) and four[0] < one[0]
