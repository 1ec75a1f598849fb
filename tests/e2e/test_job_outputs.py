"""A job on the simulated cell leaves report.html, the deviation PLY, the E57 and the pose log next to
cloud.ply, and report.json carries the same inspection numbers and the coverage."""

from __future__ import annotations

import csv
import json

import numpy as np
import pye57
import pytest
from job_reports import report_with_ground_truth
from tandemscan.daemon.cell.session import CellSession
from tandemscan.daemon.jobs.runner import JobRunner
from tandemscan.daemon.plans import default_plan_path
from tandemscan.pipeline.io.cloud_io import read_ply
from tandemscan.pipeline.io.export import ScanExports, write_pose_log
from tandemscan.pipeline.planning.coverage import REASON_REACH
from tandemscan.pipeline.planning.plan import LeftOutArea, Plan, Scan
from tandemscan.pipeline.stitching.worldmap import MapCloud
from tandemscan.sim_drivers.cell import with_surveyed_mounts


def perfect_correction(monkeypatch, truth_of):
    """Stands in for the correction stage: every scan gets its true pose (``truth_of(job)``, by scan index)."""
    from tandemscan.daemon.jobs import finish

    def correct_stage(job, loaded, online, backend):
        truth = truth_of(job)
        return finish.CorrectionOutcome({"enabled": True, "cpu_seconds": 0.001},
                                        tuple(truth[s.index] for s in job.scans), True)

    monkeypatch.setattr(finish, "correct_stage", correct_stage)


async def test_job_writes_report_and_exports_next_to_cloud(sim_config, tmp_path, monkeypatch):
    plan = Plan.load(default_plan_path())
    scans = [i for i, s in enumerate(plan.steps) if isinstance(s, Scan)]
    left = LeftOutArea(reason=REASON_REACH, station=3, area_m2=0.412, z_range_mm=(1400.0, 1600.0),
                       centroid_mm=(-200.0, 0.0, 1590.0))  # as a generated plan states them
    plan = plan.model_copy(update={"steps": plan.steps[: scans[1] + 1],  # the first two scans only
                                   "coverage_pct": 78.5, "left_out": [left]})
    inspection = sim_config.inspection.model_copy(update={"views": ("isometric",), "map_width_px": 300})
    config = sim_config.model_copy(update={"inspection": inspection})
    perfect_correction(monkeypatch, lambda job: job.scorer.T_W_S_true)
    async with CellSession(config) as session:
        config = with_surveyed_mounts(config, session.cell.simulation, tmp_path)
        result = await JobRunner(session, plan, config, tmp_path / "job").run()
    job = result.job_dir
    for name in ("cloud.ply", "report.html", "report.json", "cloud_deviation.ply", "cloud.e57", "poses.csv"):
        assert (job / name).is_file(), name
    report = report_with_ground_truth(job)  # report.json and the simulator's scores beside it
    assert len(read_ply(job / "cloud.ply")[0]) == report["points_cloud"]  # written on a thread, complete
    # report.html is written after the last scan, before report.json
    assert report["timings"]["after_last_scan_s"] > 0
    assert report["timings"]["correction_cpu_s"] == report["correction"]["cpu_seconds"] > 0
    assert 0.1 < report["resources"]["peak_rss_gib"] < 64  # this process's peak until then (VmHWM)
    # the simulator scores after the outputs are written: the tracker-only stitch (its scans merged again at
    # the tracker poses) as ``correction.before``, the (perfect) correction as ``ground_truth``
    before, truth = report["correction"]["before"], report["ground_truth"]
    assert truth["pose_err_mm_max"] < 1e-9 < before["pose_err_mm_median"]
    assert truth["scoring_s"] >= 0 and "ground_truth" not in json.loads((job / "report.json").read_text())
    ins = report["inspection"]
    assert ins["as_measured"]["stats"]["count"] == report["points_cloud"] > 1000
    # the sim cell stitches with true mounts: registered to CAD by the job's own anchor (one target reading at
    # the start, Eq. 5, no truth) the cloud lies on the part to a fraction of a millimetre ...
    assert abs(ins["as_measured"]["stats"]["mean_mm"]) < 0.2 and ins["as_measured"]["stats"]["rms_mm"] < 0.3
    assert report["relocalisation"]["anchor"]["placed"] and np.asarray(ins["T_F_W"]).shape == (4, 4)
    # ... and once best-fitted it is the cloud the ground-truth observer scored
    assert abs(ins["best_fit"]["stats"]["rms_mm"] - report["ground_truth"]["cloud_rms_mm"]) < 1e-3
    # the job aligned its cloud to the CAD itself (a best fit from the anchor, no truth) and says so; the
    # truth scorer finds the fit closer to the world's T_F_W than the anchor it started from
    assert ins["alignment"]["method"] == "best-fit" and ins["alignment"]["T_F_W"] == ins["T_F_W"]
    assert ins["verdict"] == "pass" and ins["deviations"] == []  # the defect-free part
    scored = report["ground_truth"]["inspection"]
    assert scored["T_F_W_err_mm"] < 0.5 * scored["anchor_T_F_W_err_mm"] and scored["false_regions"] == 0
    (pair,) = ins["stitching"]  # tracker-only stitch before, the (perfect) correction after
    assert pair["points"] > 100 and pair["rms_after_mm"] < pair["rms_before_mm"]
    assert pair["rms_after_mm"] < 0.1  # scanner noise only
    html = (job / "report.html").read_text()
    assert f'{ins["as_measured"]["stats"]["rms_mm"]:.4f}' in html and html.count("data:image/png") >= 3
    e57 = pye57.E57(str(job / "cloud.e57"))
    try:
        assert e57.scan_count == 3  # two poses and the merged cloud
        assert e57.get_header(2).point_count == report["points_cloud"]
        for i, entry in enumerate(report["scan_log"]):
            header = e57.get_header(i)
            assert header.point_count == entry["points"]
            np.testing.assert_allclose(header.translation * 1000.0, np.asarray(entry["T_W_S"])[:3, 3], atol=1e-6)
            assert entry["T_W_S"] != entry["T_W_S_tracker"]  # the final pose beside the tracker's
    finally:
        e57.close()
    with (job / "poses.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [int(r["points"]) for r in rows] == [e["points"] for e in report["scan_log"]]
    # coverage: the plan's share of the surface where a pose fits, the share the cloud measured (two scans: a
    # little of it) and the plan's left-out areas, which report.html lists
    coverage = report["coverage"]
    assert coverage["planned_pct"] == 78.5 and coverage["of"] == "surface where a pose fits"
    assert 0.5 < coverage["measured_pct"] < 10.0 and report["inspection"]["coverage"] == coverage
    (area,) = coverage["left_out"]
    assert area["reason"] == REASON_REACH and area["area_m2"] == 0.412
    assert area["where"] == "near AGV station 3, z 1400 to 1600 mm, centred at x -200, y 0, z 1590 mm"
    assert 'id="left-out"' in html and area["where"] in html and "planned 78.5 %" in html
    # the default part's regions, for the default part
    assert [r["name"] for r in ins["regions"]] == ["body", "nose"]


async def test_an_export_that_fails_is_named_in_the_report_and_fails_the_job(sim_config, tmp_path, monkeypatch):
    """The E57 cannot be written (a full disk): cloud.ply, the inspection and the pose log beside it are written all
    the same, report.json is written naming the failed output, and the job ends with that error (an OSError: an
    output not written, no traceback), so that a resume writes its outputs again."""
    from tandemscan.daemon.jobs import finish, outputs

    monkeypatch.setattr(outputs, "write_scan_exports", exports_on_a_full_disk)  # run in the exports' process
    plan = Plan.load(default_plan_path())
    scans = [i for i, s in enumerate(plan.steps) if isinstance(s, Scan)]
    plan = plan.model_copy(update={"steps": plan.steps[: scans[1] + 1]})  # the first two scans only
    inspection = sim_config.inspection.model_copy(update={"views": ("isometric",), "map_width_px": 300})
    config = sim_config.model_copy(update={"inspection": inspection})
    perfect_correction(monkeypatch, lambda job: job.scorer.T_W_S_true)
    async with CellSession(config) as session:
        config = with_surveyed_mounts(config, session.cell.simulation, tmp_path)
        with pytest.raises(finish.OutputsNotWritten, match="e57 not written: OSError.*No space left") as failed:
            await JobRunner(session, plan, config, tmp_path / "job").run()
    assert isinstance(failed.value, OSError)
    job = tmp_path / "job"
    report = json.loads((job / "report.json").read_text())
    assert report["failed_outputs"] == {"e57": "OSError: [Errno 28] No space left on device: "
                                                f"'{job / 'cloud.e57'}'"}
    assert str(job / "report.json") in str(failed.value)
    for name in ("cloud.ply", "report.html", "poses.csv"):
        assert (job / name).is_file(), name
    assert report["inspection"]["verdict"] == "pass" and len(read_ply(job / "cloud.ply")[0]) == report["points_cloud"]


def exports_on_a_full_disk(exports: ScanExports) -> None:
    """``export.write_scan_exports`` where the disk fills after the pose log: the E57 is not written."""
    write_pose_log(exports.pose_log, exports.scans)
    raise OSError(28, "No space left on device", str(exports.e57))


def test_inspection_skipped_with_reason(sim_config, tmp_path):
    from types import SimpleNamespace

    from tandemscan.daemon.jobs.outputs import write_job_outputs
    from tandemscan.pipeline.compute import LazyBackend

    def runner(config, T_F_W):
        worldmap = MapCloud(1.0, np.zeros((0, 3)), np.zeros((0, 3)))  # a job whose scans saw nothing
        return SimpleNamespace(job_dir=tmp_path, scans=[], worldmap=worldmap, T_F_W=T_F_W, config=config)

    off = sim_config.model_copy(update={"inspection": sim_config.inspection.model_copy(update={"in_job": False})})
    failed, backend = {}, LazyBackend(sim_config.compute)  # an untiled cloud's inspection makes none
    assert write_job_outputs(runner(off, np.eye(4)), {}, failed=failed, backend=backend)["skipped"] \
        == "inspection.in_job is off"
    # relocalisation off or target unseen
    unplaced = write_job_outputs(runner(sim_config, None), {}, failed=failed, backend=backend)
    assert unplaced["skipped"] == "no registration of the world frame to the CAD frame"
    assert write_job_outputs(runner(sim_config, np.eye(4)), {}, failed=failed, backend=backend)["skipped"] \
        == "empty cloud"
    assert failed == {}  # skipped is not failed: the pose log and the E57 were written each time
    assert (tmp_path / "poses.csv").read_text().startswith("index,name,points")
    assert not (tmp_path / "report.html").exists()


async def test_inspection_takes_at_most_max_points_of_the_cloud(sim_config, tmp_path):
    """Beyond ``[inspection] max_points`` the inspection takes every k-th point of the cloud, and says so;
    cloud.ply and the E57 keep every point."""
    plan = Plan.load(default_plan_path())
    scans = [i for i, s in enumerate(plan.steps) if isinstance(s, Scan)]
    plan = plan.model_copy(update={"steps": plan.steps[: scans[0] + 1]})
    inspection = sim_config.inspection.model_copy(update={"views": ("isometric",), "map_width_px": 300,
                                                           "max_points": 1000})
    config = sim_config.model_copy(update={"inspection": inspection})
    async with CellSession(config) as session:
        result = await JobRunner(session, plan, config, tmp_path / "job").run()
    report = json.loads((result.job_dir / "report.json").read_text())
    n = report["points_cloud"]
    assert n > 10_000 and len(read_ply(result.job_dir / "cloud.ply")[0]) == n
    step = -(-n // 1000)
    inspected = report["inspection"]["as_measured"]["stats"]["count"]
    assert inspected == len(range(0, n, step)) <= 1000
    assert len(read_ply(result.job_dir / "cloud_deviation.ply")[0]) == inspected
    assert report["inspection"]["meta"]["points"] == f"{inspected} of the cloud's {n} ([inspection] max_points)"
    # the shipped band plan states no coverage: report.html does not say it leaves nothing out
    assert report["coverage"]["planned_pct"] is None and report["coverage"]["left_out"] == []
    assert "The plan states no coverage" in (result.job_dir / "report.html").read_text()



async def test_a_job_whose_alignment_fails_reports_an_indeterminate_inspection(sim_config, tmp_path):
    """A job whose cloud cannot be aligned to the CAD (here: no fit leaves 99 % of the points within 1 um of it)
    still ends with report.html and report.json: the inspection's verdict "indeterminate" with the reason."""
    plan = Plan.load(default_plan_path())
    scans = [i for i, s in enumerate(plan.steps) if isinstance(s, Scan)]
    plan = plan.model_copy(update={"steps": plan.steps[: scans[0] + 1]})
    inspection = sim_config.inspection.model_copy(update={
        "views": ("isometric",), "map_width_px": 300, "max_points": 3000, "best_fit_max_distance_mm": 0.001,
        "alignment_min_inlier_share": 0.99})
    config = sim_config.model_copy(update={"inspection": inspection})
    async with CellSession(config) as session:
        result = await JobRunner(session, plan, config, tmp_path / "job").run()
    ins = json.loads((result.job_dir / "report.json").read_text())["inspection"]
    assert ins["verdict"] == "indeterminate" and ins["reason"].startswith("alignment to CAD failed")
    assert ins["files"]["html"] == "report.html" and "deviation_ply" not in ins["files"]
    html = (result.job_dir / "report.html").read_text()
    assert 'class="verdict indeterminate"' in html and ins["reason"][:40] in html
