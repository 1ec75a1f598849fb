"""Crash recovery of the job store: what a daemon does with its state folder before it resumes.

A scan file is durable before the journal commits it (``docs/daemon.md``, how a job survives a crash), so a crash
between the two leaves a file no committed row points to, or a half-written ``.part``: both are removed and the
step runs again on resume.
"""

from __future__ import annotations

import logging

from tandemscan.daemon.store import JobStore

log = logging.getLogger(__name__)


def remove_uncommitted_scans(store: JobStore) -> int:
    """Remove every scan file of the store's job folders that no committed scan points to; returns how many."""
    committed = store.committed_scan_files()
    removed = 0
    for job_path in store.jobs_dir.iterdir() if store.jobs_dir.exists() else ():
        scans_dir = job_path / "scans"
        if not scans_dir.is_dir():
            continue
        for f in scans_dir.iterdir():
            if f.name.endswith(".part") or (job_path.name, f.relative_to(job_path).as_posix()) not in committed:
                f.unlink()
                removed += 1
    if removed:
        log.warning("recovery removed %d uncommitted scan file(s)", removed)
    return removed


def recover(store: JobStore) -> list[str]:
    """After a restart: remove the uncommitted scan files; return the ids of the jobs that were active (to resume)."""
    remove_uncommitted_scans(store)
    return store.active_jobs()
