"""The fine stage re-selects the overlap, the final refinement follows the correspondences' own gate, the
global stages recover a pose with no usable start (the classical one the same every run), every result is
verified, and the ICP path never imports PyTorch."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from dataclasses import replace
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from tandemscan.config.models import CorrectionConfig, DeepMergeConfig
from tandemscan.daemon.cli import main
from tandemscan.pipeline.geometry.frames import from_rotvec, invert, pose_error, transform_points
from tandemscan.pipeline.registration.global_registration import FeatureMatching, fpfh_ransac
from tandemscan.pipeline.registration.icp import (
    Convergence,
    FineSchedule,
    gate_distance,
    icp_coarse_to_fine,
    icp_point_to_plane,
    iterate_point_to_plane,
    refine_at_gate,
    target_with_normals,
)
from tandemscan.pipeline.registration.pairs import (
    REFINE_SIGMAS,
    LazyNetwork,
    PairCriteria,
    RegistrationFailed,
    register_clouds,
    register_pair,
)


def criteria(**keys) -> PairCriteria:
    """The pair criteria of a ``[correction]`` section with ``keys``."""
    return PairCriteria.from_section(CorrectionConfig(**keys))


_BUMPS = np.random.default_rng(11).uniform([-90, -90, 4, -15], [90, 90, 14, 15], (40, 4))


def relief(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A terrain of 40 bumps of different sizes at fixed random places (mm): curved everywhere, no symmetry."""
    z = np.zeros_like(x)
    for cx, cy, r, h in _BUMPS:
        z += h * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * r**2))
    return z


def crops(seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Two independently sampled, partly overlapping crops (mm) of :func:`relief`: x in [-80, 30] and
    [-30, 80], y in [-80, 80]."""
    rng = np.random.default_rng(seed)
    out = []
    for lo, hi in ((-80.0, 30.0), (-30.0, 80.0)):
        xy = np.c_[rng.uniform(lo, hi, 12000), rng.uniform(-80, 80, 12000)]
        out.append(np.c_[xy, relief(xy[:, 0], xy[:, 1])] + rng.normal(0, 0.02, (12000, 3)))
    return out[0], out[1]


def moved(T_true: np.ndarray, seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """The first crop moved by ``T_true^-1`` (so ``T_true`` registers it back), and the second crop."""
    src, tgt = crops(seed)
    return transform_points(invert(T_true), src), tgt


def test_the_fine_stage_reselects_the_overlap_and_reaches_what_one_level_does_not():
    T_true = from_rotvec([3.0, -2.0, 1.5], np.radians([4.0, -3.0, 2.0]))
    source, target_pts = moved(T_true)
    target = target_with_normals(target_pts)
    one_level = icp_point_to_plane(source, target, np.eye(4), 10.0, 50).transformation
    fit = icp_coarse_to_fine(source, target, np.eye(4), FineSchedule(10.0, 1.0))
    dt1, dr1 = pose_error(one_level, T_true)
    dt, dr = pose_error(fit.transformation, T_true)
    assert np.degrees(dr) < 0.01 and dt < 0.02
    assert dt * 5 < dt1                        # the overlap at 10 mm drags a single level off
    assert 0.4 < fit.fitness < 0.8 and fit.rmse_mm < 0.05


def test_the_gate_is_the_mean_plus_sigmas_of_the_distances_within_reach():
    d = np.r_[np.random.default_rng(0).uniform(0.1, 0.9, 5000), [1.7, 2.5, np.inf]]   # beyond 1.5 mm: ignored
    inside = d[d < 1.5]
    assert gate_distance(d, 1.5, 3.0) == pytest.approx(inside.mean() + 3.0 * inside.std())
    assert gate_distance(d, 1.5, 3.0) < 1.5 and gate_distance(d, 1.5, 2.0) < gate_distance(d, 1.5, 3.0)
    assert gate_distance(d, 1.0, 3.0) == 1.0                    # never above the final distance
    assert gate_distance(np.full(5, 0.3), 1.5, 3.0) == 1.5      # too few correspondences: the final distance


def dense_crops_with_standoff(seed: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(source moved by ``T^-1``, target, ``T``): two 30,000-point crops of :func:`relief` (x in [-60, 20] and
    [-20, 60], y in [-60, 60]) where 15 % of the source's points in one corner of the overlap stand 1.1-1.45
    mm off the surface (mixed pixels at an edge): within a 1.5 mm correspondence distance, not within the
    true correspondences' spread."""
    rng = np.random.default_rng(seed)
    out = []
    for lo, hi in ((-60.0, 20.0), (-20.0, 60.0)):
        xy = np.c_[rng.uniform(lo, hi, 30000), rng.uniform(-60, 60, 30000)]
        out.append(np.c_[xy, relief(xy[:, 0], xy[:, 1])] + rng.normal(0, 0.02, (30000, 3)))
    src, tgt = out
    corner = np.flatnonzero((src[:, 0] > -20) & (src[:, 1] > 20))
    corner = corner[rng.random(len(corner)) < 0.15]
    src[corner, 2] += rng.uniform(1.1, 1.45, len(corner))
    T_true = from_rotvec([1.0, -0.5, 0.5], np.radians([0.5, -0.3, 0.2]))
    return transform_points(invert(T_true), src), tgt, T_true


def test_the_final_refinement_at_the_gate_drops_what_the_fixed_distance_lets_pull():
    source, target_pts, T_true = dense_crops_with_standoff()
    target = target_with_normals(target_pts)
    fit = icp_coarse_to_fine(source, target, np.eye(4), FineSchedule(5.0, 1.5))
    refined, gate = refine_at_gate(source, target, fit.transformation, 1.5)
    _, dr_fixed = pose_error(fit.transformation, T_true)
    dt, dr = pose_error(refined, T_true)
    assert 0.5 < gate < 1.5
    assert np.degrees(dr_fixed) > 0.08                       # the standoff points pull the fit at 1.5 mm
    assert np.degrees(dr) < 0.04 and dt < 0.05 and dr < dr_fixed / 3
    # register_pair refines only when asked (the job's pairs do not): without, it is the fine stage's answer
    cfg = criteria(method="icp", icp_max_distance_mm=1.5)
    plain = register_pair(source, target, cfg, None, 5.0)
    assert plain.gate_mm is None and np.array_equal(plain.transformation, fit.transformation)
    # asked (register's default), its levels stop at a repeated correspondence set, then it refines
    stopped = icp_coarse_to_fine(source, target, np.eye(4), FineSchedule(5.0, 1.5, stop_on_repeat=True))
    expected, expected_gate = refine_at_gate(source, target, stopped.transformation, 1.5, REFINE_SIGMAS)
    asked = register_pair(source, target, cfg, None, 5.0, REFINE_SIGMAS)
    assert asked.gate_mm == expected_gate and np.array_equal(asked.transformation, expected)
    assert register_clouds(source, target_pts, cfg).gate_mm == pytest.approx(expected_gate)
    assert np.degrees(pose_error(expected, T_true)[1]) < 0.04
    # ``deepmerge`` stays the network's own answer: not refined
    answer = from_rotvec([0.3, 0.0, 0.0], np.radians([0.05, 0.0, 0.0])) @ T_true
    alone = register_pair(source, target, replace(cfg, method="deepmerge"), FixedAnswer(answer), 5.0, REFINE_SIGMAS)
    assert alone.gate_mm is None and np.array_equal(alone.transformation, answer)


class FixedAnswer:
    """A registrar that always answers the same ``T_target_source`` (stands in for the network)."""

    def __init__(self, T: np.ndarray) -> None:
        self.T = T

    def register(self, source_mm: np.ndarray, target_mm: np.ndarray) -> np.ndarray:
        return self.T


def test_stopping_at_a_repeated_correspondence_set_keeps_a_converging_fit():
    T_true = from_rotvec([1.0, -0.5, 0.5], np.radians([0.5, -0.3, 0.2]))
    source, target_pts = moved(T_true)
    target = target_with_normals(target_pts)
    start = from_rotvec([0.2, 0.1, -0.1], np.radians([0.05, 0.0, -0.05])) @ T_true
    open3ds = iterate_point_to_plane(source, target, start, 1.5, Convergence())
    ours = iterate_point_to_plane(source, target, start, 1.5, Convergence(stop_on_repeat=True))
    dt, dr = pose_error(ours, open3ds)
    assert np.degrees(dr) < 1e-5 and dt < 1e-5


def test_fpfh_ransac_gives_the_same_answer_every_run_and_leaves_open3ds_threads_as_they_were():
    T_true = from_rotvec([8.0, -6.0, 5.0], np.radians([10.0, -25.0, 30.0]))
    source, target = moved(T_true)
    threads = o3d.utility.get_max_threads()
    answers = [fpfh_ransac(source, target, FeatureMatching()) for _ in range(3)]
    assert all(np.array_equal(a, answers[0]) for a in answers)
    assert o3d.utility.get_max_threads() == threads


def test_fpfh_ransac_finds_a_large_rotation_without_a_start():
    T_true = from_rotvec([8.0, -6.0, 5.0], np.radians([10.0, -25.0, 30.0]))
    source, target = moved(T_true)
    dt, dr = pose_error(fpfh_ransac(source, target, FeatureMatching()), T_true)
    assert np.degrees(dr) < 3.0 and dt < 5.0


@pytest.mark.slow
def test_auto_recovers_an_arbitrary_pose_and_says_which_stage_won():
    T_true = from_rotvec([8.0, -6.0, 5.0], np.radians([10.0, -25.0, 30.0]))
    source, target = moved(T_true)
    res = register_clouds(source, target, criteria(method="auto", icp_max_distance_mm=1.0), delta_mm=1e4,
                          network=LazyNetwork(DeepMergeConfig()))
    dt, dr = pose_error(res.transformation, T_true)
    assert np.degrees(dr) < 0.02 and dt < 0.05
    # from 40 deg the fine stage alone lands elsewhere, so the two disagree and the network runs as well
    assert res.stage in ("fpfh", "deepmerge") and res.stages_run == ("init", "fpfh", "deepmerge")
    assert res.cost_mm2 < res.start_cost_mm2 and res.fit.inliers > 1000


def test_a_pair_without_overlap_is_refused_not_returned():
    source, target = moved(from_rotvec([500.0, 0.0, 0.0], [0.0, 0.0, 0.0]))
    with pytest.raises(RegistrationFailed, match="no inliers"):
        register_clouds(source, target, criteria(method="icp"), delta_mm=5.0)


def _write(path, points: np.ndarray) -> str:
    o3d.io.write_point_cloud(str(path), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)))
    return str(path)


def test_register_exits_3_with_one_line_when_the_fit_fails(tmp_path, capsys):
    source, target = moved(from_rotvec([500.0, 0.0, 0.0], [0.0, 0.0, 0.0]))
    a, b = _write(tmp_path / "a.ply", source), _write(tmp_path / "b.ply", target)
    assert main(["register", a, b, "--method", "icp"]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("registration failed: no inliers")


def test_register_prints_the_transform_and_the_winning_stage(tmp_path, capsys):
    T_true = from_rotvec([1.0, -0.5, 0.5], np.radians([0.5, -0.3, 0.2]))
    source, target = moved(T_true)
    a, b = _write(tmp_path / "a.ply", source), _write(tmp_path / "b.ply", target)
    assert main(["register", a, b, "--method", "icp", "--out", str(tmp_path / "T.txt")]) == 0
    out = capsys.readouterr().out
    assert "stage init won of init" in out
    dt, dr = pose_error(np.loadtxt(tmp_path / "T.txt"), T_true)
    assert dt < 0.02 and np.degrees(dr) < 0.03              # from 0.6 deg, at the default 2 mm distance


def _modules_after(code: str) -> set[str]:
    """The modules a fresh interpreter holds after running ``code``."""
    probe = code + "\nimport sys\nprint(' '.join(sorted(sys.modules)))\n"
    run = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True, timeout=240)
    return set(run.stdout.split())


def test_register_icp_imports_neither_torch_nor_open3d(tmp_path):
    T_true = from_rotvec([1.0, -0.5, 0.5], np.radians([0.5, -0.3, 0.2]))
    source, target = moved(T_true)
    a, b = _write(tmp_path / "a.ply", source), _write(tmp_path / "b.ply", target)
    mods = _modules_after(f"from tandemscan.daemon.cli import main\nassert main(['register', {a!r}, {b!r}, "
                          f"'--method', 'icp']) == 0")
    assert "tandemscan.pipeline.registration.pairs" in mods and "torch" not in mods and "open3d" not in mods


def test_the_jobs_icp_correction_does_not_import_torch():
    mods = _modules_after(textwrap.dedent(f'''
        import sys
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from test_registration_correction import scans_with_drift
        from tandemscan.config.models import CorrectionConfig, DeepMergeConfig
        from tandemscan.pipeline.registration.correction import CorrectionSettings, StitchedJob, correct_scans
        from tandemscan.pipeline.registration.pairs import LazyNetwork
        truth, scans, transfers = scans_with_drift(n=4)
        cfg = CorrectionSettings.from_section(CorrectionConfig(method="icp", min_overlap_points=100))
        res = correct_scans(StitchedJob(scans, transfers), cfg, LazyNetwork(DeepMergeConfig()))
        assert res.report["pairs"] >= 3
    '''))
    assert "tandemscan.pipeline.registration.correction" in mods and "torch" not in mods


@pytest.mark.slow
def test_register_icp_from_40_deg_is_refused_by_its_fit_not_returned(tmp_path, capsys):
    """From 40 deg with an overlap threshold that takes every point, the fine stage alone lands in a wrong
    minimum that still beats its start: ``register --method icp`` refuses it by the absolute criterion (its
    RMS spreads over the correspondence gate), one line and exit 3; from 0.6 deg it is accepted."""
    T_true = from_rotvec([8.0, -6.0, 5.0], np.radians([10.0, -25.0, 30.0]))
    source, target = moved(T_true)
    cfg = criteria(method="icp", icp_max_distance_mm=1.0)
    with pytest.raises(RegistrationFailed, match="poor fit: point-to-plane RMS"):
        register_clouds(source, target, cfg, delta_mm=1e4)
    a, b = _write(tmp_path / "a.ply", source), _write(tmp_path / "b.ply", target)
    conf = tmp_path / "cell.toml"
    conf.write_text("[correction]\nicp_max_distance_mm = 1.0\n")
    assert main(["register", a, b, "--method", "icp", "--delta-mm", "10000", "--config", str(conf)]) == 3
    said = capsys.readouterr()
    assert said.out == "" and len(said.err.strip().splitlines()) == 1
    assert said.err.startswith("registration failed: poor fit")
    good = register_clouds(*moved(from_rotvec([1.0, -0.5, 0.5], np.radians([0.5, -0.3, 0.2]))), cfg, delta_mm=5.0)
    assert good.fit.rmse_mm < 0.1 * cfg.icp_max_distance_mm
