"""A full disk during a daemon job (a 64 MB tmpfs as the state folder, mounted in a user and mount namespace by
``tests/disk_full_child.py``): the job leaves ``running`` with a storage reason, health says so, nothing committed
is lost, and once space returns the held state is journaled and a resumed job completes with every scan once."""

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


def run_disk_full(tmp_path: Path) -> dict:
    """The child's outcome (its last output line)."""
    proc = subprocess.run(["unshare", "--user", "--map-root-user", "--mount", sys.executable, str(CHILD),
                           str(tmp_path)], capture_output=True, text=True, timeout=600)
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
