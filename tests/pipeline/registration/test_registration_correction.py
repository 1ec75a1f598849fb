"""Whole-job correction: synthetic overlapping scans with drift across tracker stations, known truth."""

from __future__ import annotations

import numpy as np
import pytest
from tandemscan.config.models import CorrectionConfig
from tandemscan.pipeline.geometry.frames import compose, from_rotvec, invert, pose_error, transform_points
from tandemscan.pipeline.registration import correction, pairs
from tandemscan.pipeline.registration.correction import CorrectionSettings, StitchedJob, StitchedScan, correct_scans
from tandemscan.pipeline.registration.icp import target_with_normals
from tandemscan.pipeline.registration.pairs import JobPairSettings, PairCriteria, correct_pair, register_pair
from tandemscan.pipeline.registration.pose_graph import TransferPrior


def surface(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return 10 * np.sin(x / 37.0) * np.cos(y / 29.0) + 6 * np.cos(x / 61.0 + y / 45.0)


TRANSFER_COV = np.diag([0.25**2] * 3 + [np.radians(0.04) ** 2] * 3)


def scans_with_drift(n: int = 6, per_station: int = 2, seed: int = 0):
    """Scans 300 mm wide every 150 mm along x (half overlap); each later station carries a transfer drift
    about the still target (at the station's first scan). Returns the truth, the scans, the transfer priors."""
    rng = np.random.default_rng(seed)
    truth, scans, transfers = [], [], []
    drift = np.eye(4)
    sig_t, sig_r = 0.01, np.radians(0.001)
    cov = np.diag([sig_t**2] * 3 + [sig_r**2] * 3)
    for i in range(n):
        k = i // per_station
        if i and k != (i - 1) // per_station:                          # a transfer, about the target
            c = np.array([150.0 * i, 0, 440.0])
            step = from_rotvec(rng.normal(0, 0.25, 3), rng.normal(0, np.radians(0.04), 3))
            drift = from_rotvec(c, [0, 0, 0]) @ step @ from_rotvec(-c, [0, 0, 0]) @ drift
            transfers.append(TransferPrior(k, c, TRANSFER_COV))
        xy = np.c_[rng.uniform(150 * i - 150, 150 * i + 150, 9000), rng.uniform(-100, 100, 9000)]
        P_W = np.c_[xy, surface(xy[:, 0], xy[:, 1])]
        T_W_S = from_rotvec([150.0 * i, 0, 440.0], [np.pi, 0, 0])
        P_S = transform_points(invert(T_W_S), P_W)
        P_S[:, 2] += rng.normal(0, 0.05, len(P_S))                      # noise along the view
        noise = from_rotvec(rng.normal(0, sig_t, 3), rng.normal(0, sig_r, 3))
        truth.append(T_W_S)
        scans.append(StitchedScan(P_S, compose(drift, noise, T_W_S), cov, k))
    return truth, scans, transfers


@pytest.mark.parametrize("joint", [True, False], ids=["joint refinement", "pose graph"])
def test_icp_correction_and_its_refinement_remove_transfer_drift(joint, monkeypatch):
    truth, scans, transfers = scans_with_drift()
    cfg = CorrectionSettings.from_section(CorrectionConfig(method="icp", min_overlap_points=100, joint=joint))
    if joint:  # the pose graph is not solved where the joint refinement gives the poses
        monkeypatch.setattr(correction, "refine_poses", lambda *a, **k: pytest.fail("pose graph solved"))
    res = correct_scans(StitchedJob(scans, transfers), cfg)
    assert res.report["pairs"] >= 5
    assert ("joint" in res.report) is joint
    assert ("graph_cost_after" in res.report) is not joint and ("graph_s" in res.report["stage_seconds"]) is not joint
    if not joint:
        assert res.report["graph_cost_after"] < res.report["graph_cost_before"]
    before = np.array([pose_error(s.T_W_S, X)[0] for s, X in zip(scans, truth, strict=True)])
    after = np.array([pose_error(T, X)[0] for T, X in zip(res.poses, truth, strict=True)])
    assert np.median(after[2:]) * 5 < np.median(before[2:])
    assert res.report["overlap_rms_mm_median_after"] < res.report["overlap_rms_mm_median_before"]
    assert res.report["overlap_rms_mm_median_after"] < 0.1


def test_correct_pair_needs_overlap_and_a_delta():
    truth, scans, _ = scans_with_drift(n=2, per_station=1)
    a = transform_points(scans[0].T_W_S, scans[0].points_S)
    b = transform_points(scans[1].T_W_S, scans[1].points_S)
    cfg = JobPairSettings.from_section(CorrectionConfig(method="icp", overlap_delta_mm=3.0))
    target = target_with_normals(a)
    pc = correct_pair(b, target, cfg, None)
    assert pc is not None and pc.overlap_points > 1000 and pc.delta_mm == 3.0 and pc.stage == "init"
    assert pc.fit.rmse_mm < pc.rmse_before_mm
    far = b + [5000.0, 0, 0]
    assert correct_pair(far, target, cfg, None) is None
    with pytest.raises(ValueError, match="overlap_delta_mm"):
        correct_pair(b, target, JobPairSettings.from_section(CorrectionConfig(method="icp")), None)


@pytest.mark.parametrize("reach", [2.0, 1.001], ids=["within reach", "moved beyond: again whole"])
def test_a_pair_on_its_source_within_reach_is_the_whole_sources_to_the_bit(reach, monkeypatch):
    """``correct_pair`` registers only the source points within ``REACH_MULTIPLE`` times the largest
    correspondence distance of the target: correction, fit, overlap and centre are the whole source's to the bit.
    Where the fit moves a point left out farther than that allows (a reach of 1.001 times), the whole source is
    registered again."""
    _, scans, _ = scans_with_drift(n=2, per_station=1)
    a = transform_points(scans[0].T_W_S, scans[0].points_S)
    b = transform_points(from_rotvec([0.2, -0.1, 0.1], np.radians([0.01, -0.02, 0.01])),
                         transform_points(scans[1].T_W_S, scans[1].points_S))
    cfg = JobPairSettings.from_section(CorrectionConfig(method="icp", overlap_delta_mm=1.5))
    monkeypatch.setattr(pairs, "REACH_MULTIPLE", 1e9)  # every source point within reach: the whole source
    whole = correct_pair(b, target_with_normals(a), cfg, None)
    sizes, real = [], pairs._correct_from_stitch
    monkeypatch.setattr(pairs, "_correct_from_stitch", lambda S, *args: sizes.append(len(S)) or real(S, *args))
    monkeypatch.setattr(pairs, "REACH_MULTIPLE", reach)
    part = correct_pair(b, target_with_normals(a), cfg, None)
    assert sizes[0] < 0.8 * len(b) and sizes[1:] == ([] if reach > 1.5 else [len(b)])
    np.testing.assert_array_equal(part.transformation, whole.transformation)
    np.testing.assert_array_equal(part.fit.points_mm, whole.fit.points_mm)
    np.testing.assert_array_equal(part.centre_mm, whole.centre_mm)
    assert (part.fit.fitness, part.fit.rmse_mm, part.rmse_before_mm, part.overlap_points) == (
        whole.fit.fitness, whole.fit.rmse_mm, whole.rmse_before_mm, whole.overlap_points)
    assert pose_error(whole.transformation, np.eye(4))[0] > 0.05  # the fit moved the source


def bumpy(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A surface curved enough to fix all six degrees of freedom of a 160 mm patch."""
    return 10 * np.sin(x / 17.0) * np.cos(y / 13.0) + 6 * np.cos(x / 23.0 + y / 19.0)


def test_the_guard_keeps_a_closer_fit_and_rejects_a_worse_one():
    from tandemscan.pipeline.registration.pairs import keep_if_better

    rng = np.random.default_rng(5)
    xy = rng.uniform(-80, 80, (6000, 2))
    P = np.c_[xy, bumpy(xy[:, 0], xy[:, 1])]
    T_true = from_rotvec([0.8, -0.5, 0.3], np.radians([0.3, -0.2, 0.2]))
    source, target = transform_points(invert(T_true), P[::2]), target_with_normals(P[1::2])
    # the true transform moves boundary points out of the overlap but fits much closer: kept
    np.testing.assert_array_equal(keep_if_better(source, target, T_true, 3.0), T_true)
    worse = from_rotvec([-1.0, 0.5, 0.0], np.radians([0.0, 0.5, -0.4])) @ invert(T_true)
    np.testing.assert_array_equal(keep_if_better(source, target, worse, 3.0), np.eye(4))


@pytest.mark.slow
def test_deepmerge_then_icp_on_a_pair_recovers_the_correction():
    from tandemscan.pipeline.deepmerge.register import DeepMergeRegistrar

    rng = np.random.default_rng(4)
    xy = rng.uniform(-80, 80, (6000, 2))
    P = np.c_[xy, bumpy(xy[:, 0], xy[:, 1])]
    T_true = from_rotvec([0.5, -0.3, 0.2], np.radians([0.2, 0.1, -0.3]))
    source, target = transform_points(invert(T_true), P[::2]), target_with_normals(P[1::2])
    cfg = PairCriteria.from_section(CorrectionConfig(method="deepmerge+icp"))
    reg = DeepMergeRegistrar.load(num_points=256)
    res = register_pair(source, target, cfg, reg, start_distance_mm=3.0)
    dt, dr = pose_error(res.transformation, T_true)
    assert dt < 0.05 and np.degrees(dr) < 0.02 and res.stage == "deepmerge"
    with pytest.raises(ValueError, match="registrar"):
        register_pair(source, target, PairCriteria.from_section(CorrectionConfig(method="deepmerge")), None, 3.0)


def test_a_pair_that_fails_its_verification_gets_no_edge_and_is_logged(monkeypatch, caplog):
    from tandemscan.pipeline.registration import pair_stage, pairs

    truth, scans, transfers = scans_with_drift()
    cfg = CorrectionSettings.from_section(CorrectionConfig(method="icp", min_overlap_points=100))
    real = pairs.correct_pair

    def refuse_the_cross_station_pair(source_W, target, cfg_, network, cov=None):
        pc = real(source_W, target, cfg_, network, cov)
        if np.allclose(source_W.mean(axis=0)[0], 150.0 * 2, atol=60.0):   # scan 2, the first of station 1
            raise pairs.RegistrationFailed("fit worse than the start (test)")
        return pc

    full = correct_scans(StitchedJob(scans, transfers), cfg)
    monkeypatch.setattr(pair_stage, "correct_pair", refuse_the_cross_station_pair)
    with caplog.at_level("WARNING", logger="tandemscan.pipeline.registration.correction"):
        res = correct_scans(StitchedJob(scans, transfers), cfg)
    dropped = res.report["pairs_dropped"]
    assert dropped and all(d["j"] == 2 and "worse than the start" in d["reason"] for d in dropped)
    assert res.report["pairs"] == full.report["pairs"] - len(dropped)
    assert all((i, j) != (d["i"], d["j"]) for i, j, _ in res.edges for d in dropped)
    assert any("dropped" in r.getMessage() and "(1, 2)" in r.getMessage() for r in caplog.records)
    assert full.report["pairs_dropped"] == [] and full.report["stages"] == {"init": full.report["pairs"]}


def test_the_stages_parameters_are_the_sections_keys_of_the_same_names():
    """``CorrectionSettings.from_section`` takes each stage's parameters from ``[correction]``, once: the pair
    criteria, the job's pair settings and the joint refinement's (its ``joint_*`` keys)."""
    from dataclasses import FrozenInstanceError

    from tandemscan.config.models import DeepMergeConfig

    section = CorrectionConfig(method="auto", icp_max_distance_mm=1.25, job_pair_iterations=7, overlap_delta_mm=2.5,
                               joint_voxel_mm=3.0, joint_max_distance_mm=0.8, joint_iterations=3, joint_sigma_mm=0.04)
    s = CorrectionSettings.from_section(section)
    assert s.method == s.pairs.criteria.method == "auto" and s.pairs.criteria.icp_max_distance_mm == 1.25
    assert s.pairs.job_pair_iterations == 7 and s.pairs.overlap_delta_mm == 2.5 and s.joint_voxel_mm == 3.0
    assert (s.joint_refinement.max_distance_mm, s.joint_refinement.iterations, s.joint_refinement.sigma_mm) == (
        0.8, 3, 0.04)
    assert PairCriteria.from_section(section, method="icp").method == "icp"
    with pytest.raises(FrozenInstanceError):
        s.pairs.criteria.icp_iterations = 1
    with pytest.raises(AttributeError, match="icp_max_distance_mm|method"):  # a section without the stage's keys
        PairCriteria.from_section(DeepMergeConfig())


def test_with_the_joint_refinement_only_the_check_pairs_are_registered_and_give_no_pose(monkeypatch):
    """The joint refinement starts from the tracker poses and takes nothing from the pairs' outcomes: with it only
    each scan's ``check_partners_per_scan`` best-overlap partners of its station and of the others are registered
    (the report's pair figures), and the poses, the joint's figures and the overlap RMS (on the pairs selected at
    ``max_partners_per_scan`` either way) are the same to the bit with no pair registered at all."""
    from tandemscan.pipeline.registration.overlap import overlapping_pairs

    _, scans, transfers = scans_with_drift(n=8, per_station=3)
    registered, real = [], correction.register_units
    monkeypatch.setattr(correction, "register_units", lambda units, *a, **k: registered.extend(
        (u.target.index, s.index) for u in units for s in u.sources) or real(units, *a, **k))

    def run(**keys):
        registered.clear()
        cfg = CorrectionSettings.from_section(CorrectionConfig(method="icp", min_overlap_points=100, **keys))
        return correct_scans(StitchedJob(scans, transfers), cfg), sorted(registered)

    checked, pairs_checked = run()
    world = [transform_points(s.T_W_S, s.points_S) for s in scans]
    stations = [s.station for s in scans]
    assert pairs_checked == overlapping_pairs(world, stations, 10.0, 1)
    assert len(pairs_checked) < len(overlapping_pairs(world, stations, 10.0, 6))
    assert any(stations[i] != stations[j] for i, j in pairs_checked)  # the transfers' links among them
    assert 0 < checked.report["pairs"] + len(checked.report["pairs_dropped"]) <= len(pairs_checked)
    unchecked, pairs_unchecked = run(check_partners_per_scan=0)
    assert pairs_unchecked == [] and unchecked.report["pairs"] == 0 and unchecked.edges == []
    graph, pairs_graph = run(joint=False)
    assert pairs_graph == overlapping_pairs(world, stations, 10.0, 6)
    for a, b in zip(checked.poses, unchecked.poses, strict=True):
        np.testing.assert_array_equal(a, b)
    for key in ("joint", "overlap_rms_mm_median_before", "pose_change_mm_median"):
        assert checked.report[key] == unchecked.report[key]
    assert checked.report["overlap_rms_mm_median_before"] == graph.report["overlap_rms_mm_median_before"]


@pytest.mark.parametrize("failing", ["a scan's summary", "a pair"])
def test_a_correction_whose_unit_raises_leaves_no_joint_scans_in_the_store(failing, monkeypatch, tmp_path):
    """The scans read from the scan store (this process holds none of their points): the summary units write each
    scan prepared for the joint refinement to ``joint/``; a later unit raising (the last scan's summary, a check
    pair's registration) fails the correction, which leaves no ``joint/`` folder behind."""
    from tandemscan.pipeline.compute import LocalBackend
    from tandemscan.pipeline.io.raw_scan import write_raw_scan
    from tandemscan.pipeline.registration import pair_stage

    _, scans, transfers = scans_with_drift(n=4, per_station=2)
    (tmp_path / "scans").mkdir()
    stored = []
    for k, s in enumerate(scans):
        write_raw_scan(tmp_path / f"scans/scan-{k}.npz", points_S_mm=s.points_S)
        stored.append(StitchedScan(None, s.T_W_S, s.covariance, s.station, f"scans/scan-{k}.npz"))
    written = []
    read, write = pair_stage.StoredScans.loaded, correction.StoredJointScan.write

    def loaded(store, ref):
        if failing == "a scan's summary" and ref.index == len(stored) - 1:
            raise OSError("the store went away")
        return read(store, ref)

    def registered(*args, **kwargs):
        raise RuntimeError("a worker's bad day")

    def noted(*args):
        written.append(write(*args))
        return written[-1]

    monkeypatch.setattr(pair_stage.StoredScans, "loaded", loaded)
    monkeypatch.setattr(pair_stage, "register_unit", registered)
    monkeypatch.setattr(correction.StoredJointScan, "write", noted)
    settings = CorrectionSettings.from_section(CorrectionConfig(method="icp", min_overlap_points=100))
    with pytest.raises(OSError if failing == "a scan's summary" else RuntimeError):
        correct_scans(StitchedJob(stored, transfers, voxel_mm=1.0), settings, backend=LocalBackend(1),
                      scan_store=str(tmp_path))
    assert written  # the units before it wrote theirs
    assert not (tmp_path / correction.JOINT_FOLDER).exists()
    assert sorted(p.name for p in (tmp_path / "scans").iterdir()) == [f"scan-{k}.npz" for k in range(4)]
