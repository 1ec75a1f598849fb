"""A full disk during a daemon job (a 64 MB tmpfs as the state folder, mounted in a user and mount namespace by
``tests/e2e/disk_full_child.py``): the job leaves ``running`` with a storage reason, health says so, nothing
committed is lost, and once space returns the held state is journaled and a resumed job completes with every scan
once."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

CHILD = Path(__file__).with_name("disk_full_child.py")


def _namespaces_work() -> bool:
    if shutil.which("unshare") is None:
        return False
    probe = subprocess.run(["unshare", "--user", "--map-root-user", "--mount", "true"], capture_output=True)
    return probe.returncode == 0


def run_disk_full(tmp_path: Path, phase: str = "scan") -> dict:
    """The child's outcome (its last output line); the disk fills in ``phase`` (``scan`` or ``export``)."""
    proc = subprocess.run(["unshare", "--user", "--map-root-user", "--mount", sys.executable, str(CHILD),
                           str(tmp_path), phase], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not _namespaces_work(), reason="needs unprivileged user and mount namespaces (a tmpfs)")
def test_a_full_disk_pauses_the_job_loudly_and_it_completes_once_space_returns(tmp_path):
    out = run_disk_full(tmp_path)
    assert out["left_running_s"] is not None
    assert out["state_on_full_disk"] == "paused_fault" and out["reason"].startswith("storage fault"), out
    health = out["health_on_full_disk"]
    assert health["status"] == "degraded" and health["storage_low"] and health["free_bytes"] < 4_000_000
    assert out["guard_free_bytes"] < out["guard_needs_bytes"]
    committed = out["committed_scans_on_full_disk"]
    assert committed and out["scan_steps"][: len(committed)] == committed  # nothing committed lost
    assert out["journaled_state_after_space_returned"] == "paused_fault"
    assert out["final_state"] == "succeeded", out["final_error"]
    assert out["scan_steps"] == [2, 4, 8] and out["report_scans"] == 3
    assert out["scan_files"] == ["scan-0000.npz", "scan-0001.npz", "scan-0002.npz"]
    if os.environ.get("TANDEMSCAN_FAULT_MATRIX"):
        with open(os.environ["TANDEMSCAN_FAULT_MATRIX"], "a", encoding="utf-8") as f:
            f.write(json.dumps({"fault": "disk full during a job (64 MB tmpfs)", "outcome": "paused_fault, resumed "
                                "after space returned, succeeded", "reason": out["reason"],
                                "left_running_s": out["left_running_s"], "health": health["status"],
                                "scans": len(out["scan_steps"])}) + "\n")


@pytest.mark.skipif(not _namespaces_work(), reason="needs unprivileged user and mount namespaces (a tmpfs)")
def test_a_full_disk_during_the_export_pauses_and_the_job_completes_with_its_report(tmp_path):
    """Issue 42 row 3: numpy's ``tofile`` raises an ``OSError`` without errno on a full disk; the export pauses like
    any phase, and once space returns the resumed job writes report.json with every scan once."""
    out = run_disk_full(tmp_path, "export")
    assert out["state_on_full_disk"] == "paused_fault" and out["reason"].startswith("storage fault (disk full)"), out
    assert out["committed_scans_on_full_disk"] == [2, 4, 8]  # every step was committed before the export
    assert out["final_state"] == "succeeded", out["final_error"]
    assert out["scan_steps"] == [2, 4, 8] and out["report_scans"] == 3 and out["report_attempts"] == 2
    assert out["report_resumes"] == [{"step": 9, "kind": "export"}]  # issue 42 row 7: a resume in the export
    assert out["scan_files"] == ["scan-0000.npz", "scan-0001.npz", "scan-0002.npz"]


@pytest.mark.skipif(not _namespaces_work(), reason="needs unprivileged user and mount namespaces (a tmpfs)")
def test_safety_events_reach_subscribers_and_systemd_while_the_journal_is_full(tmp_path):
    """Issue 42 row 6: with the journal refusing writes, each safety event is still published (without an id) and
    sent to systemd; the refused writes are counted and retried, and every event is journaled once space returns;
    no task dies unobserved."""
    out = run_disk_full(tmp_path, "events")
    reasons = out["reasons"]
    full = out["health_while_full"]
    assert full["event_journal_failures"] > 0 and full["events_not_journaled"] > 0, out
    assert full["status"] == "degraded"
    assert out["published_reasons"] == reasons and out["published_unjournaled"] > 0
    assert out["notified"][-2:] == [f"STATUS=safety stop: {reasons[-1]}", "STATUS=safety stop reset"]
    assert len(out["notified"]) == 2 * len(reasons)
    assert out["journaled_reasons"] == reasons  # each retried until the journal took it, in order
    assert out["health_after"]["events_not_journaled"] == 0
    assert out["loop_errors"] == []
