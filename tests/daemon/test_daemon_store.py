"""The job store: journal, idempotency, exactly-once steps, durable scan files and crash recovery."""

from __future__ import annotations

import asyncio
import os
import signal
import sqlite3
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from tandemscan.daemon.store.job_store import IdempotencyConflict, JobStore, StoreError, recover
from tandemscan.pipeline.io.raw_scan import RawScanError, read_raw_scan, write_raw_scan


def _write_scan(store, job_id, step_idx, points, normals=None):
    """A raw scan written as the runner writes it, registered for ``commit_step``."""
    path = store.job_dir(job_id) / "scans" / f"scan-{step_idx:04d}.npz"
    arrays = {"points_S_mm": points} if normals is None else {"points_S_mm": points, "normals_S": normals}
    write_raw_scan(path, **arrays)
    return store.register_scan_file(job_id, step_idx, path, len(points))


@pytest.fixture
def store(tmp_path):
    s = JobStore(tmp_path / "state")
    yield s
    s.close()


def test_journal_is_wal_and_job_has_its_own_directory(store):
    job, event = store.create_job("default", {"steps": [1, 2]}, n_steps=2)
    assert event.data == {"state": "queued"} and job.state == "queued" and job.n_steps == 2
    assert store.job_dir(job.id).is_dir()
    mode = sqlite3.connect(store.db_path).execute("PRAGMA journal_mode").fetchone()[0]
    assert mode == "wal"


def test_idempotency_key_never_creates_two_jobs(store):
    a, created_a = store.create_job("p", {}, 1, idempotency_key="k1", request_hash="h")
    b, created_b = store.create_job("p", {}, 1, idempotency_key="k1", request_hash="h")
    assert created_a is not None and created_b is None and a.id == b.id
    with pytest.raises(IdempotencyConflict):
        store.create_job("p", {}, 1, idempotency_key="k1", request_hash="other")
    assert store.list_jobs()[1] == 1


def test_list_filters_and_pages_newest_first(store):
    ids = [store.create_job("a" if i % 2 else "b", {}, 1)[0].id for i in range(5)]
    store.set_state(ids[0], "running")
    page, total = store.list_jobs(limit=2, offset=1)
    assert total == 5 and [j.id for j in page] == [ids[3], ids[2]]
    running, n = store.list_jobs(states=["running"])
    assert n == 1 and running[0].id == ids[0] and running[0].started_s is not None
    assert store.list_jobs(plan_name="a")[1] == 2


def test_final_state_is_never_left(store):
    job, _ = store.create_job("p", {}, 1)
    store.set_state(job.id, "cancelled")
    with pytest.raises(StoreError, match="cancelled"):
        store.set_state(job.id, "running")
    with pytest.raises(StoreError):
        store.get_job("nope")


def test_step_commits_once_with_its_result_and_scan(store):
    job, _ = store.create_job("p", {}, 3)
    pts = np.random.default_rng(0).normal(size=(100, 3)).astype(np.float32)
    pending = _write_scan(store, job.id, 1, pts, -pts)
    T = np.eye(4)
    assert store.commit_step(job.id, 0, "move_arm", {"ok": True})
    assert store.commit_step(job.id, 1, "scan", {"T_C_T": T, "joints_rad": np.zeros(6)}, scan=pending)
    assert not store.commit_step(job.id, 1, "scan", {"n": 100})
    assert sorted(store.committed_steps(job.id)) == [0, 1] and store.steps_done(job.id) == 2
    [scan] = store.scans(job.id)
    assert scan.step_idx == 1
    p, n = read_raw_scan(store.job_dir(job.id) / scan.file)
    np.testing.assert_array_equal(p, pts)
    np.testing.assert_array_equal(n, -pts)
    result = store.committed_steps(job.id)[1]
    assert result["T_C_T"] == T.tolist() and result["joints_rad"] == [0.0] * 6


def test_events_are_journaled_in_order(store):
    job, _ = store.create_job("p", {}, 4)
    store.set_state(job.id, "running")
    store.set_progress(job.id, 25.0, 1, {"rms_mm": 0.1})
    ev = store.events(job_id=job.id)
    assert [e.kind for e in ev] == ["state", "state", "progress"]
    assert ev[-1].data["figures"] == {"rms_mm": 0.1}
    assert store.events(after_seq=ev[1].seq)[0].seq == ev[2].seq == store.last_event_seq()
    assert store.get_job(job.id).progress == 25.0


_CRASHER = textwrap.dedent("""
    import os, signal, sys
    import numpy as np
    from tandemscan.daemon.store.job_store import JobStore
    from tandemscan.pipeline.io.raw_scan import write_raw_scan
    store = JobStore(sys.argv[1])
    job, _ = store.create_job("p", {}, 3)
    store.set_state(job.id, "running")
    scans = store.job_dir(job.id) / "scans"
    write_raw_scan(scans / "scan-0000.npz", points_S_mm=np.ones((10, 3)))
    store.commit_step(job.id, 0, "scan", {}, scan=store.register_scan_file(job.id, 0, scans / "scan-0000.npz", 10))
    write_raw_scan(scans / "scan-0001.npz", points_S_mm=np.ones((20, 3)))  # on disk and fsynced, never committed
    print(job.id, flush=True)
    os.kill(os.getpid(), signal.SIGKILL)
""")


def test_kill_between_scan_write_and_commit_then_reopen(tmp_path):
    state = tmp_path / "state"
    proc = subprocess.run([sys.executable, "-c", _CRASHER, str(state)], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    job_id = proc.stdout.split()[0]
    orphan = state / "jobs" / job_id / "scans" / "scan-0001.npz"
    assert orphan.exists()
    store = JobStore(state)
    try:
        assert recover(store) == [job_id]
        assert not orphan.exists()
        assert sorted(store.committed_steps(job_id)) == [0]
        assert [s.step_idx for s in store.scans(job_id)] == [0]
        assert read_raw_scan(state / "jobs" / job_id / store.scans(job_id)[0].file)[0].shape == (10, 3)
        # the resumed run commits step 1 exactly once
        store.commit_step(job_id, 1, "scan", {}, scan=_write_scan(store, job_id, 1, np.ones((20, 3))))
        assert [s.step_idx for s in store.scans(job_id)] == [0, 1]
        assert sorted(os.listdir(state / "jobs" / job_id / "scans")) == ["scan-0000.npz", "scan-0001.npz"]
    finally:
        store.close()


def test_half_written_part_file_is_removed(store):
    job, _ = store.create_job("p", {}, 1)
    part = store.job_dir(job.id) / "scans" / "scan-0000.npz.part"
    part.parent.mkdir(parents=True)
    part.write_bytes(b"half")
    recover(store)
    assert not part.exists()


def test_bad_scan_shape_is_a_clear_error(store):
    job, _ = store.create_job("p", {}, 1)
    with pytest.raises(RawScanError, match=r"\(N, 3\)"):
        _write_scan(store, job.id, 0, np.ones((4, 2)))
    with pytest.raises(RawScanError, match="do not match"):
        _write_scan(store, job.id, 0, np.ones((4, 3)), np.ones((3, 3)))
    assert not (store.job_dir(job.id) / "scans" / "scan-0000.npz").exists()


def test_two_restarts_on_the_same_step_are_two_resumes(tmp_path):
    from tandemscan.daemon.jobs.journal import StoreJournal
    from tandemscan.daemon.jobs.manager import JobContext

    store = JobStore(tmp_path)
    job, _ = store.create_job("p", {"plan": {}}, 10)
    for _ in range(3):  # the first run, then two restarts that both resume at step 4
        attempt = store.begin_attempt(job.id)
        if attempt.attempts > 1:
            journal = StoreJournal(JobContext(attempt, store, None, None))
            asyncio.run(journal.record_resume(4, {"step": 4, "kind": "scan", "attempt": attempt.attempts}))
    assert [r["attempt"] for r in store.resumes(job.id)] == [2, 3]
    store.close()


def test_job_states_change_only_along_the_state_machine(store):
    from tandemscan.daemon.job_state import JobState, TransitionError, check_transition

    assert check_transition("paused_fault", "running") is JobState.RUNNING
    assert check_transition("queued", "queued") is JobState.QUEUED  # a waiting reason written again
    for current, new in (("queued", "paused"), ("succeeded", "running"), ("running", "nonsense")):
        with pytest.raises(TransitionError):
            check_transition(current, new)
    job, _ = store.create_job("p", {}, 1)
    with pytest.raises(StoreError, match="a queued job cannot become paused_safety"):
        store.set_state(job.id, "paused_safety")


def test_jobs_are_counted_by_state_in_one_query(store):
    a, _ = store.create_job("default", {}, n_steps=1)
    b, _ = store.create_job("default", {}, n_steps=1)
    store.create_job("default", {}, n_steps=1)
    store.set_state(a.id, "running")
    store.set_state(b.id, "cancelled")
    assert store.count_by_state() == {"queued": 1, "running": 1, "cancelled": 1}
