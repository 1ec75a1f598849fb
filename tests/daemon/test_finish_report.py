"""The report of a job's end (daemon/jobs/finish.py ``report_job``): what fails beside the outputs is named in the
report, which is written all the same."""

from __future__ import annotations

import time

import pytest
from tandemscan.config.models import ComputeConfig
from tandemscan.daemon.jobs import finish, pose_correction
from tandemscan.daemon.jobs.outputs import JobExports
from tandemscan.daemon.jobs.snapshot import JobSnapshot
from tandemscan.pipeline.compute import LazyBackend


@pytest.fixture
def written(monkeypatch):
    """``build_job_report`` and ``write_job_report`` replaced by recorders of what the report was built from."""
    seen = {}

    def build_job_report(job, seconds, tracker_poses, inspection, coverage, peak_rss_gib, timings, failed=None):
        seen.update(correction=job.correction, timings=timings, failed=failed)
        return "report"

    monkeypatch.setattr(finish, "build_job_report", build_job_report)
    monkeypatch.setattr(finish, "write_job_report", lambda report, job_dir: seen.setdefault("written", report))
    return seen


def _outputs(tmp_path, checks: object | None, failed: dict[str, str]) -> finish.JobOutputs:
    section = {"enabled": True, "method": "icp", "scans": 2, "overlap_rms_mm_median_after": 0.05}
    job = JobSnapshot(tmp_path, None, None, None, [], [], section, None)
    return finish.JobOutputs(job, finish.CorrectionOutcome(section, (), True, None, checks),
                             JobExports({}, {}, None, {"exports_and_inspection_s": 1.0}, failed), None, None, 1.0,
                             {"merge_s": 1.0}, LazyBackend(ComputeConfig()))


def test_check_pairs_that_cannot_be_registered_are_named_in_the_correction_section(written, monkeypatch, tmp_path):
    def complete_checks(job, checks, later, backend):
        raise RuntimeError("scan store unreachable")

    monkeypatch.setattr(pose_correction, "complete_checks", complete_checks)
    finished = finish.report_job(_outputs(tmp_path, object(), {}), time.monotonic(), None)
    assert written["written"] == "report" == finished.report
    assert written["correction"] == finished.correction.section == {
        "enabled": True, "method": "icp", "scans": 2, "pair_checks_failed": "RuntimeError: scan store unreachable",
        "overlap_rms_mm_median_after": 0.05}  # in the place of the pair figures
    assert list(written["correction"]) == ["enabled", "method", "scans", "pair_checks_failed",
                                           "overlap_rms_mm_median_after"]
    assert finished.correction.checks is None and "pair_checks_s" in written["timings"].stages_s


def test_an_output_not_written_fails_the_job_once_the_report_names_it(written, tmp_path):
    failed = {"cloud_ply": "OSError: [Errno 28] No space left on device"}
    with pytest.raises(finish.OutputsNotWritten, match="cloud_ply not written: OSError") as raised:
        finish.report_job(_outputs(tmp_path, None, failed), time.monotonic(), None)
    assert isinstance(raised.value, OSError)
    assert written["written"] == "report" and written["failed"] == failed  # written before the job fails
