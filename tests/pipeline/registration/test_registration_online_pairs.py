"""Pairs registered while the job measures: the end of the job reuses them and gets the same result."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from tandemscan.config.models import CorrectionConfig
from tandemscan.pipeline.geometry.frames import from_rotvec
from tandemscan.pipeline.registration.correction import (
    CorrectionSettings,
    OnlineWork,
    StitchedJob,
    StitchedScan,
    correct_scans,
)
from tandemscan.pipeline.registration.online_pairs import OnlinePairs
from test_registration_correction import scans_with_drift


def settings(**keys) -> CorrectionSettings:
    """The correction's parameters of a ``[correction]`` section with ``keys``."""
    return CorrectionSettings.from_section(CorrectionConfig(**keys))


def _measure(scans, transfers, cfg, voxel_mm=1.0) -> OnlinePairs:
    """The scans arriving one at a time, each with the transfers journaled before it."""
    online = OnlinePairs(cfg, voxel_mm)
    for s in scans:
        online.add(s.points_S, s.T_W_S, s.covariance, s.station, [t for t in transfers if t.station <= s.station])
    online.work()
    return online


def test_the_end_of_the_job_reuses_every_pair_and_gets_the_same_poses():
    _, scans, transfers = scans_with_drift(n=6, per_station=2)
    cfg = settings(method="icp", min_overlap_points=100, joint=False)
    online = _measure(scans, transfers, cfg)
    assert online.outcomes
    fresh = correct_scans(StitchedJob(scans, transfers), cfg)
    reused = correct_scans(StitchedJob(scans, transfers), cfg, online=online.work())
    assert fresh.report["pairs_registered_while_measuring"] == 0
    selected = fresh.report["pairs"] + sum(1 for _ in fresh.report["pairs_dropped"])
    assert reused.report["pairs_registered_while_measuring"] >= selected
    for a, b in zip(fresh.poses, reused.poses, strict=True):  # Open3D's threaded sums: not bit for bit
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)


def test_a_scan_whose_pose_changed_is_registered_again_at_the_end():
    _, scans, transfers = scans_with_drift(n=4, per_station=4)
    cfg = settings(method="icp", min_overlap_points=100, joint=False)
    online = _measure(scans, transfers, cfg)
    moved = list(scans)
    moved[3] = StitchedScan(scans[3].points_S, from_rotvec([0.3, 0, 0], [0, 0, 0]) @ scans[3].T_W_S,
                            scans[3].covariance, scans[3].station)
    res = correct_scans(StitchedJob(moved, transfers), cfg, online=online.work())
    fresh = correct_scans(StitchedJob(moved, transfers), cfg)
    pairs_with_3 = sum(1 for i, j, _ in fresh.edges if 3 in (i, j))
    assert pairs_with_3 > 0
    assert res.report["pairs_registered_while_measuring"] == fresh.report["pairs"] - pairs_with_3
    for a, b in zip(fresh.poses, res.poses, strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)


def test_methods_with_the_network_register_nothing_while_measuring():
    _, scans, transfers = scans_with_drift(n=3)
    online = _measure(scans, transfers, settings(method="deepmerge+icp"))
    assert online.outcomes == {}


@pytest.mark.parametrize("reassociate_mm", [None, 0.01])
def test_scans_prepared_for_the_joint_refinement_while_measuring_give_the_same_poses(monkeypatch, reassociate_mm):
    """With ``joint`` on, every scan is thinned and given normals as it arrives, and its pairs' nearest
    neighbours are found at the tracker poses; the end of the job takes the scans out of the cache (none is
    prepared again, none kept after), searches no pair's neighbours at the tracker poses again (only those of
    the pairs that moved after the first linearisation, found anew there) and refines to the poses it computes
    without them. A scan whose points differ from what was prepared (another voxel) is prepared again, and its
    pairs searched again. With ``joint_reassociate_mm`` off nothing is searched at the end."""
    from tandemscan.pipeline.registration import correction, joint

    _, scans, transfers = scans_with_drift(n=4, per_station=2)
    cfg = settings(method="icp", min_overlap_points=100, joint=True, joint_iterations=2,
                   joint_reassociate_mm=reassociate_mm)
    online = _measure(scans, transfers, cfg)
    work = online.work()
    assert len(work.joint_scans) == len(scans)
    fresh = correct_scans(StitchedJob(scans, transfers), cfg)
    assert fresh.report["joint"]["pairs_associated_while_measuring"] == 0
    prepared_at_end, searched_at_end = [], []
    # the refinement's searches: whole (``associate``'s), or again from the pair's last one where it moved a little
    real, real_search, real_again = correction.joint_scan, joint._nearest, joint._nearest_again

    def search_again(*args):
        found = real_again(*args)
        if found is not None:  # else searched whole
            searched_at_end.append(1)
        return found

    monkeypatch.setattr(correction, "joint_scan", lambda P, c: prepared_at_end.append(len(P)) or real(P, c))
    monkeypatch.setattr(joint, "_nearest", lambda *a: searched_at_end.append(1) or real_search(*a))
    monkeypatch.setattr(joint, "_nearest_again", search_again)
    kept = dict(work.joint_scans)
    reused = correct_scans(StitchedJob(scans, transfers), cfg, online=work)
    anew = reused.report["joint"]["pairs_associated_anew"]
    assert prepared_at_end == [] and len(searched_at_end) == anew
    assert anew > 0 if reassociate_mm else anew == 0
    assert reused.report["joint"]["pairs"] == fresh.report["joint"]["pairs"] > 0
    assert reused.report["joint"]["pairs_associated_while_measuring"] >= fresh.report["joint"]["pairs"]
    assert work.joint_scans == {}  # taken out as used: none outlives the refinement
    for a, b in zip(fresh.poses, reused.poses, strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)
    searched_before = len(searched_at_end)
    coarser = replace(cfg, joint_voxel_mm=3.0)
    correct_scans(StitchedJob(scans, transfers), coarser, online=OnlineWork(work.pairs, kept, work.associations))
    assert len(prepared_at_end) == len(scans) and len(searched_at_end) > searched_before



def test_a_scans_pairs_register_on_both_cores_while_measuring(monkeypatch):
    """The middle scan, measured last, has a partner on each side: its two pairs register at the same time (each
    waits for the other to have started), with the outcomes of one pair at a time."""
    import threading

    from tandemscan.pipeline.registration import online_pairs

    _, scans, transfers = scans_with_drift(n=3, per_station=3)
    scans = [scans[0], scans[2], scans[1]]
    cfg = settings(method="icp", min_overlap_points=100, joint=False)
    one_at_a_time = _measure(scans, transfers, cfg).outcomes
    monkeypatch.setattr("os.cpu_count", lambda: 2)
    both_running, real = threading.Barrier(2, timeout=10), online_pairs.register_stitched_pair
    middle = threading.Event()

    def meet(*args):
        if middle.is_set():
            both_running.wait()  # returns only when the other pair is registering too
        return real(*args)

    monkeypatch.setattr(online_pairs, "register_stitched_pair", meet)
    online = OnlinePairs(cfg, 1.0)
    for s in scans[:2]:
        online.add(s.points_S, s.T_W_S, s.covariance, s.station, transfers)
    middle.set()
    assert online.add(scans[2].points_S, scans[2].T_W_S, scans[2].covariance, scans[2].station, transfers) == 2
    online.work()
    assert online.outcomes.keys() == one_at_a_time.keys()
    for key, outcome in one_at_a_time.items():
        np.testing.assert_array_equal(online.outcomes[key].transformation, outcome.transformation)


@pytest.mark.parametrize("check", [1, 0])
def test_with_the_joint_refinement_only_the_check_pairs_register_while_measuring(check):
    """With ``joint`` the scans are prepared for it as they arrive and only the check pairs
    (``check_partners_per_scan``) are registered: the end of the job finds every one of them registered
    already; with none asked for, none is registered and the joint refinement still takes every prepared scan."""
    _, scans, transfers = scans_with_drift(n=6, per_station=3)
    cfg = settings(method="icp", min_overlap_points=100, check_partners_per_scan=check)
    online = _measure(scans, transfers, cfg)
    everything = _measure(scans, transfers, settings(method="icp", min_overlap_points=100, joint=False))
    assert len(online.outcomes) < len(everything.outcomes) if check else online.outcomes == {}
    work = online.work()
    assert len(work.joint_scans) == len(scans)
    res = correct_scans(StitchedJob(scans, transfers), cfg, online=work)
    assert res.report["pairs_registered_while_measuring"] >= res.report["pairs"] + len(res.report["pairs_dropped"])
    assert (res.report["pairs"] > 0) is bool(check)
    cpu = res.report["cpu_s_a_pair_while_measuring"]  # the registrations' own threads' CPU, each pair's share
    assert cpu > 0 if check else cpu is None
    assert res.report["joint"]["pairs_associated_while_measuring"] >= res.report["joint"]["pairs"] > 0


def test_check_pairs_still_registering_leave_the_poses_alone_and_complete_the_same_figures(monkeypatch, tmp_path):
    """With the joint refinement the end of the job takes the prepared scans while check pairs still register
    (``OnlinePairs.joint_work``), and prepares itself those the worker did not (``stop_preparing``, the job having
    measured its last scan): the poses are those of the end that waited for them, the report lacks only the
    pair figures, and completed from the pairs handed over later (``complete_pair_checks``) the section is the same;
    pairs the worker never handed over are registered from the scan store, with the same figures."""
    import threading

    from tandemscan.pipeline.io.raw_scan import write_raw_scan
    from tandemscan.pipeline.registration import online_pairs
    from tandemscan.pipeline.registration.correction import complete_pair_checks, with_pair_figures

    _, scans, transfers = scans_with_drift(n=6, per_station=3)
    scans = [replace(s, points_S=s.points_S.astype(np.float32).astype(float), file=f"scan-{k}.npz")
             for k, s in enumerate(scans)]  # as stored: float32
    for s in scans:
        write_raw_scan(tmp_path / s.file, points_S_mm=s.points_S)
    cfg = settings(method="icp", min_overlap_points=100, joint_iterations=2)
    waited = correct_scans(StitchedJob(scans, transfers), cfg, online=_measure(scans, transfers, cfg).work())
    assert waited.checks is None and waited.report["pairs"] > 0

    release, real = threading.Event(), online_pairs.register_stitched_pair
    monkeypatch.setattr(online_pairs, "register_stitched_pair", lambda *a: release.wait(10) and real(*a))
    online = OnlinePairs(cfg, 1.0)
    for k, s in enumerate(scans):
        if k == 4:  # the job measured its last scan: the worker leaves the last two to the end to prepare
            online.stop_preparing()
        online.add(s.points_S, s.T_W_S, s.covariance, s.station, [t for t in transfers if t.station <= s.station])
    early = online.joint_work()
    assert early.pending and early.pairs == {} and len(early.joint_scans) == 4
    assert online.joint.joint_scans == {}  # handed over, not kept
    result = correct_scans(StitchedJob(scans, transfers), cfg, online=early)
    assert result.checks is not None and "pairs" not in result.report and "pairs_dropped" not in result.report
    for a, b in zip(waited.poses, result.poses, strict=True):
        np.testing.assert_array_equal(a, b)
    release.set()
    later = online.work()
    completed = with_pair_figures(result.report, complete_pair_checks(result.checks, cfg, later, str(tmp_path), 1.0))
    timeless = {"stage_seconds", "cpu_s_a_pair_while_measuring", "joint"}  # what took how long where
    assert list(completed) == list(waited.report)  # the same section, in the same order
    assert {k: v for k, v in completed.items() if k not in timeless} == {
        k: v for k, v in waited.report.items() if k not in timeless}
    late = completed["joint"].pop("pairs_associated_while_measuring")
    assert late < waited.report["joint"].pop("pairs_associated_while_measuring")  # the last two's: at the end
    assert completed["joint"] == waited.report["joint"]
    from_store = complete_pair_checks(result.checks, cfg, None, str(tmp_path), 1.0)
    assert from_store["pairs_registered_while_measuring"] == 0
    assert {k: from_store[k] for k in ("pairs", "pairs_dropped", "stages")} == {
        k: waited.report[k] for k in ("pairs", "pairs_dropped", "stages")}
