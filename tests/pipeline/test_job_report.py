"""report.json is one frozen, typed model (``pipeline.job_report.JobReport``): its file's layout, and the two
files it is written to (report.json, and the observer's ground_truth.json beside it) holding the model's JSON."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from job_reports import report_with_ground_truth
from tandemscan.pipeline.job_report import (
    GroundTruth,
    JobHistory,
    JobReport,
    ScanEntry,
    Timings,
    as_matrix,
    write_ground_truth,
    write_job_report,
)


def _report(**changes) -> JobReport:
    pose = np.eye(4)
    pose[:3, 3] = (1.5, -2.25, 3.0)
    scans = (ScanEntry(0, 1, 1200, "scan-0000.npz", as_matrix(pose), as_matrix(np.eye(4))),
             ScanEntry(1, 1, 0, "scan-0001.npz", as_matrix(np.eye(4))))
    report = JobReport(
        job="job-1", plan="band", transfers=0, points_raw=1200, points_cloud=900, voxel_mm=1.0,
        installation_source="nominal", seconds=12.5, scans_planned=3, left_out_by_plan=({"reason": "reach"},),
        transfer_log=(), relocalisation={"untracked": [{"step": 4}], "located": []},
        correction={"enabled": True, "cpu_seconds": 0.5}, scan_log=scans, inspection={"skipped": "off"},
        coverage={"planned_pct": 80.0}, peak_rss_gib=0.75, timings=Timings(3.25, 0.5, {"merge_s": 0.25}),
        ground_truth=GroundTruth({"pose_err_mm_median": 0.01}, {"pose_err_mm_median": 0.05}, {"method": "best-fit"}),
        history=JobHistory(({"step": 2, "kind": "scan"},), 2))
    return dataclasses.replace(report, **changes)


def test_the_reports_files_hold_the_model_and_it_is_frozen(tmp_path):
    report = _report()
    with pytest.raises(ValueError, match="beside"):  # the observer's scores are not report.json's
        write_job_report(report, tmp_path)
    written = json.loads(write_job_report(dataclasses.replace(report, ground_truth=None), tmp_path).read_text())
    assert "ground_truth" not in written and "before" not in written["correction"]
    write_ground_truth(report.ground_truth, tmp_path)
    doc = report.to_json()
    assert report_with_ground_truth(tmp_path) == json.loads(json.dumps(doc))  # the two files: the model's JSON
    # the layout: derived counts, the simulator's tracker-only scores in the correction section, the
    # journal's resumes and the scans it left out at the top level
    assert doc["scans"] == 2 and doc["scans_empty"] == [1]
    assert doc["correction"] == {"enabled": True, "cpu_seconds": 0.5, "before": {"pose_err_mm_median": 0.05}}
    assert doc["ground_truth"] == {"pose_err_mm_median": 0.01, "inspection": {"method": "best-fit"}}
    assert doc["resumes"] == [{"step": 2, "kind": "scan"}] and doc["attempts"] == 2
    assert doc["scans_left_out"] == [{"step": 4}]
    assert doc["scan_log"][0]["T_W_S"][0][3] == 1.5 and "T_W_S_tracker" not in doc["scan_log"][1]
    plain = _report(ground_truth=None, history=None)  # a real cell's job run without a journal
    doc = plain.to_json()
    assert "ground_truth" not in doc and "before" not in doc["correction"] and "resumes" not in doc
    write_job_report(plain, tmp_path / "plain")
    assert report_with_ground_truth(tmp_path / "plain") == json.loads(json.dumps(doc))  # no ground_truth.json
    with pytest.raises(dataclasses.FrozenInstanceError):
        report.seconds = 1.0
