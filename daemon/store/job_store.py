"""The job store: one directory per job and a SQLite journal (WAL) of jobs, steps, notes, resumes, scans and events.

Layout under the state directory::

    journal.sqlite            jobs, steps, notes, resumes, scans, events (WAL mode, synchronous=FULL)
    jobs/<job id>/scans/      one raw scan file per scan step (``step_0007.npz``: points_mm, normals)
    jobs/<job id>/            artifacts: cloud.ply, report.json, ...

Durability rules: a scan file is written to a temporary name, fsynced, renamed and its directory fsynced
*before* the transaction that records it commits; the same transaction marks its step done. A crash
between the two leaves an orphan file that :func:`tandemscan.daemon.store.job_store.recover` removes, and the step is
run again.
Every step commits at most once (primary key ``(job_id, idx)``), so a resumed job has every scan exactly once.
Each scan row carries the file's size and SHA-256 (:meth:`JobStore.damaged_scans` checks them before a resumed job
reuses the files; :meth:`JobStore.uncommit_damaged_scan` takes a damaged one's step back out).

This module is the SQL: the folders are :mod:`.job_folders`, the rows it returns :mod:`.rows`, the
per-thread connections :mod:`.sqlite_db`, the allowed state changes :mod:`tandemscan.daemon.job_state`.

Units: mm, rad, 4x4 float64 matrices stored as nested JSON lists; times are Unix seconds.
"""

from __future__ import annotations

import json
import logging
import sqlite3
import time
import uuid
from collections.abc import Iterable
from pathlib import Path

from tandemscan.daemon.job_state import ACTIVE_STATES, FINAL_STATES, JobState, TransitionError, check_transition
from tandemscan.daemon.jsonable import jsonable
from tandemscan.daemon.store.job_folders import JobFolders, file_sha256
from tandemscan.daemon.store.rows import (
    DAMAGED_NOTE,
    CommittedScan,
    DamagedScan,
    Event,
    IdempotencyConflict,
    JobRecord,
    PendingScan,
    StoreError,
)
from tandemscan.daemon.store.sqlite_db import SqliteDb

__all__ = ["DamagedScan", "Event", "IdempotencyConflict", "JobRecord", "JobStore", "PendingScan", "CommittedScan",
           "StoreError"]

log = logging.getLogger(__name__)


# notes: what a step under way recorded before it committed; a step's result (its poses among it) is in steps
_SCHEMA = """
CREATE TABLE IF NOT EXISTS notes (
    job_id TEXT NOT NULL REFERENCES jobs(id), step_idx INTEGER NOT NULL, kind TEXT NOT NULL,
    value_json TEXT NOT NULL, t_s REAL NOT NULL, PRIMARY KEY (job_id, step_idx, kind)
);
CREATE TABLE IF NOT EXISTS jobs (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    id TEXT NOT NULL UNIQUE,
    state TEXT NOT NULL,
    plan_name TEXT NOT NULL,
    plan_json TEXT NOT NULL,
    n_steps INTEGER NOT NULL,
    idempotency_key TEXT UNIQUE,
    request_hash TEXT,
    created_s REAL NOT NULL,
    started_s REAL,
    finished_s REAL,
    updated_s REAL NOT NULL,
    progress REAL NOT NULL DEFAULT 0,
    current_step INTEGER,
    error TEXT,
    figures_json TEXT NOT NULL DEFAULT '{}',
    attempts INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX IF NOT EXISTS jobs_state ON jobs(state);
CREATE TABLE IF NOT EXISTS steps (
    job_id TEXT NOT NULL REFERENCES jobs(id),
    idx INTEGER NOT NULL,
    kind TEXT NOT NULL,
    result_json TEXT NOT NULL,
    committed_s REAL NOT NULL,
    PRIMARY KEY (job_id, idx)
);
CREATE TABLE IF NOT EXISTS scans (
    job_id TEXT NOT NULL REFERENCES jobs(id),
    step_idx INTEGER NOT NULL,
    file TEXT NOT NULL,
    n_points INTEGER NOT NULL,
    bytes INTEGER NOT NULL,
    t_s REAL NOT NULL,
    sha256 TEXT,
    PRIMARY KEY (job_id, step_idx)
);
CREATE TABLE IF NOT EXISTS resumes (
    job_id TEXT NOT NULL REFERENCES jobs(id), attempt INTEGER NOT NULL, step_idx INTEGER NOT NULL,
    value_json TEXT NOT NULL, t_s REAL NOT NULL, PRIMARY KEY (job_id, attempt)
);
CREATE TABLE IF NOT EXISTS events (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    job_id TEXT,
    kind TEXT NOT NULL,
    data_json TEXT NOT NULL,
    t_s REAL NOT NULL
);
"""

#: what a failed write of the journal or a file raises
STORAGE_ERRORS = (OSError, sqlite3.OperationalError, sqlite3.DatabaseError)


class JobStore(JobFolders):
    """The journal and the job directories under ``state_dir``. Thread-safe: one SQLite connection per
    thread (WAL lets readers run beside the writer), writes serialised by a lock (:mod:`.sqlite_db`)."""

    def __init__(self, state_dir: Path | str):
        super().__init__(state_dir)
        self.db_path = self.state_dir / "journal.sqlite"
        self._db = SqliteDb(self.db_path, _SCHEMA)
        self._conn, self._tx = self._db.conn, self._db.tx
        if "sha256" not in {r["name"] for r in self._conn().execute("PRAGMA table_info(scans)")}:
            with self._tx() as conn:  # a journal from before scans carried their checksum
                conn.execute("ALTER TABLE scans ADD COLUMN sha256 TEXT")

    def close(self) -> None:
        """Close every connection this store opened (any thread)."""
        self._db.close()

    # ------------------------------------------------------------ jobs

    def create_job(
        self, plan_name: str, plan: dict, n_steps: int, idempotency_key: str | None = None,
        request_hash: str | None = None,
    ) -> tuple[JobRecord, Event | None]:
        """Queue a new job; returns ``(job, its "queued" event)``.

        With an ``idempotency_key`` already used for the same ``request_hash`` the existing job comes back
        with no event; with a different hash :class:`IdempotencyConflict` is raised.
        """
        now = time.time()
        job_id = uuid.uuid4().hex[:16]
        with self._tx() as conn:
            if idempotency_key is not None:
                row = conn.execute("SELECT * FROM jobs WHERE idempotency_key = ?", (idempotency_key,)).fetchone()
                if row is not None:
                    if row["request_hash"] != request_hash:
                        raise IdempotencyConflict(
                            f"Idempotency-Key {idempotency_key!r} was used for a different request")
                    return _job_from_row(row), None
            conn.execute(
                "INSERT INTO jobs (id, state, plan_name, plan_json, n_steps, idempotency_key, request_hash,"
                " created_s, updated_s) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (job_id, JobState.QUEUED, plan_name, json.dumps(plan), n_steps, idempotency_key, request_hash, now,
                 now),
            )
            event = self._event(conn, job_id, "state", {"state": JobState.QUEUED}, now)
        self.job_dir(job_id).mkdir(parents=True, exist_ok=True)
        return self.get_job(job_id), event

    def get_job(self, job_id: str) -> JobRecord:
        """The job, or :class:`StoreError` when unknown."""
        row = self._conn().execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if row is None:
            raise StoreError(f"no job {job_id!r}")
        return _job_from_row(row)

    def list_jobs(
        self, states: Iterable[str] | None = None, plan_name: str | None = None,
        created_after_s: float | None = None, limit: int = 50, offset: int = 0,
    ) -> tuple[list[JobRecord], int]:
        """Jobs newest first, filtered; returns ``(page, total matching)``."""
        where, args = [], []
        states = list(states or [])
        if states:
            where.append(f"state IN ({','.join('?' * len(states))})")
            args.extend(states)
        if plan_name is not None:
            where.append("plan_name = ?")
            args.append(plan_name)
        if created_after_s is not None:
            where.append("created_s > ?")
            args.append(created_after_s)
        clause = f" WHERE {' AND '.join(where)}" if where else ""
        conn = self._conn()
        total = conn.execute(f"SELECT COUNT(*) FROM jobs{clause}", args).fetchone()[0]
        rows = conn.execute(
            f"SELECT * FROM jobs{clause} ORDER BY seq DESC LIMIT ? OFFSET ?", [*args, limit, offset]).fetchall()
        return [_job_from_row(r) for r in rows], total

    def count_by_state(self) -> dict[str, int]:
        """``{state: number of jobs}`` of the states some job is in (one grouped count)."""
        rows = self._conn().execute("SELECT state, COUNT(*) AS n FROM jobs GROUP BY state").fetchall()
        return {r["state"]: r["n"] for r in rows}

    def next_queued(self) -> JobRecord | None:
        """The oldest queued job."""
        row = self._conn().execute("SELECT * FROM jobs WHERE state = ? ORDER BY seq LIMIT 1",
                                   (JobState.QUEUED,)).fetchone()
        return None if row is None else _job_from_row(row)

    def set_state(self, job_id: str, state: str, error: str | None = None) -> tuple[JobRecord, Event]:
        """Change a job's state (:func:`~tandemscan.daemon.job_state.check_transition`); returns the job and the
        journaled event."""
        now = time.time()
        with self._tx() as conn:
            row = conn.execute("SELECT state, started_s, error FROM jobs WHERE id = ?", (job_id,)).fetchone()
            if row is None:
                raise StoreError(f"no job {job_id!r}")
            try:
                state = str(check_transition(row["state"], state))
            except TransitionError as e:
                raise StoreError(f"job {job_id}: {e}") from e
            started = row["started_s"] if row["started_s"] is not None or state != JobState.RUNNING else now
            finished = now if state in FINAL_STATES else None
            if error is None and state not in (JobState.QUEUED, JobState.RUNNING, JobState.SUCCEEDED):
                error = row["error"]  # a pause or failure keeps the reason it had; a fresh run clears it
            conn.execute(
                "UPDATE jobs SET state = ?, error = ?, started_s = ?, finished_s = ?, updated_s = ? WHERE id = ?",
                (state, error, started, finished, now, job_id),
            )
            data = {"state": state} if error is None else {"state": state, "error": error}
            event = self._event(conn, job_id, "state", data, now)
        return self.get_job(job_id), event

    def begin_attempt(self, job_id: str) -> JobRecord:
        """Count one more start of the job's runner (the first run, then each daemon restart during it)."""
        with self._tx() as conn:
            conn.execute("UPDATE jobs SET attempts = attempts + 1, updated_s = ? WHERE id = ?", (time.time(), job_id))
        return self.get_job(job_id)

    def set_progress(self, job_id: str, progress: float, current_step: int | None,
                     figures: dict | None = None) -> Event:
        """Record progress (0-100), the step under way and optional figures so far; journaled as an event."""
        now = time.time()
        data = {"progress": round(float(progress), 3), "current_step": current_step}
        with self._tx() as conn:
            if figures is None:
                conn.execute("UPDATE jobs SET progress = ?, current_step = ?, updated_s = ? WHERE id = ?",
                             (progress, current_step, now, job_id))
            else:
                conn.execute(
                    "UPDATE jobs SET progress = ?, current_step = ?, figures_json = ?, updated_s = ? WHERE id = ?",
                    (progress, current_step, json.dumps(figures), now, job_id))
                data["figures"] = figures
            return self._event(conn, job_id, "progress", data, now)

    # ------------------------------------------------------------ steps, poses, scans

    def note(self, job_id: str, step_idx: int, kind: str, value: dict) -> None:
        """Durably record something about a step under way (kept whether or not the step commits)."""
        with self._tx() as conn:
            conn.execute("INSERT OR REPLACE INTO notes (job_id, step_idx, kind, value_json, t_s)"
                         " VALUES (?, ?, ?, ?, ?)", (job_id, step_idx, kind, json.dumps(jsonable(value)), time.time()))

    def notes(self, job_id: str, step_idx: int) -> dict[str, dict]:
        """``{kind: value}`` noted for one step."""
        rows = self._conn().execute("SELECT kind, value_json FROM notes WHERE job_id = ? AND step_idx = ?",
                                    (job_id, step_idx)).fetchall()
        return {r["kind"]: json.loads(r["value_json"]) for r in rows}

    def add_resume(self, job_id: str, attempt: int, step_idx: int, value: dict) -> None:
        """Durably record how attempt ``attempt`` of the job resumed at ``step_idx`` (one row per attempt, so two
        restarts on the same step are two resumes)."""
        with self._tx() as conn:
            conn.execute("INSERT OR REPLACE INTO resumes (job_id, attempt, step_idx, value_json, t_s)"
                         " VALUES (?, ?, ?, ?, ?)",
                         (job_id, attempt, step_idx, json.dumps(jsonable(value)), time.time()))

    def resumes(self, job_id: str) -> list[dict]:
        """Every resume of the job, in attempt order."""
        rows = self._conn().execute("SELECT value_json FROM resumes WHERE job_id = ? ORDER BY attempt",
                                    (job_id,)).fetchall()
        return [json.loads(r["value_json"]) for r in rows]

    def commit_step(self, job_id: str, step_idx: int, kind: str, result: dict | None = None,
                    scan: PendingScan | None = None) -> bool:
        """Commit one step atomically: its result (JSON-able: the raw poses it measured) and its scan file.

        Returns False (and changes nothing) when the step was already committed.
        """
        now = time.time()
        with self._tx() as conn:
            exists = conn.execute("SELECT 1 FROM steps WHERE job_id = ? AND idx = ?", (job_id, step_idx)).fetchone()
            if exists:
                return False
            conn.execute("INSERT INTO steps (job_id, idx, kind, result_json, committed_s) VALUES (?, ?, ?, ?, ?)",
                         (job_id, step_idx, kind, json.dumps(jsonable(result or {})), now))
            if scan is not None:
                if scan.step_idx != step_idx:
                    raise StoreError(f"scan of step {scan.step_idx} committed with step {step_idx}")
                rel = scan.path.relative_to(self.job_dir(job_id)).as_posix()
                conn.execute("INSERT INTO scans (job_id, step_idx, file, n_points, bytes, t_s, sha256)"
                             " VALUES (?, ?, ?, ?, ?, ?, ?)",
                             (job_id, step_idx, rel, scan.n_points, scan.bytes, now, scan.sha256))
        return True

    def committed_steps(self, job_id: str) -> dict[int, dict]:
        """``{step index: result}`` of every committed step."""
        rows = self._conn().execute("SELECT idx, result_json FROM steps WHERE job_id = ? ORDER BY idx",
                                    (job_id,)).fetchall()
        return {r["idx"]: json.loads(r["result_json"]) for r in rows}

    def steps_done(self, job_id: str) -> int:
        """How many steps of the job are committed (one indexed count, no result is read)."""
        return self._conn().execute("SELECT COUNT(*) FROM steps WHERE job_id = ?", (job_id,)).fetchone()[0]

    def scans(self, job_id: str) -> list[CommittedScan]:
        """Committed scans in step order."""
        rows = self._conn().execute("SELECT * FROM scans WHERE job_id = ? ORDER BY step_idx", (job_id,)).fetchall()
        return [CommittedScan(r["job_id"], r["step_idx"], r["file"], r["n_points"], r["bytes"], r["t_s"], r["sha256"])
                for r in rows]

    def damaged_scans(self, job_id: str) -> list[DamagedScan]:
        """The job's committed scans whose file is missing, of another size or another SHA-256 than committed
        (reads every scan file: call it in a worker thread)."""
        damaged = []
        for scan in self.scans(job_id):
            path = self.job_dir(job_id) / scan.file
            if not path.is_file():
                reason = "file missing"
            elif (size := path.stat().st_size) != scan.bytes:
                reason = f"{size} bytes, {scan.bytes} committed (truncated or overwritten)"
            elif scan.sha256 is not None and file_sha256(path) != scan.sha256:
                reason = "content differs from what was committed (SHA-256)"
            else:
                continue
            result = self.committed_steps(job_id).get(scan.step_idx) or {}
            damaged.append(DamagedScan(job_id, scan.step_idx, result.get("index"), scan.file, reason))
        return damaged

    def uncommit_damaged_scan(self, damaged: DamagedScan) -> None:
        """Take a damaged scan's step back out of the journal (its step and scan rows; a ``damaged`` note on the step
        keeps what was wrong and its scan index) and remove its file, so that the step is measured again."""
        with self._tx() as conn:
            conn.execute("DELETE FROM scans WHERE job_id = ? AND step_idx = ?", (damaged.job_id, damaged.step_idx))
            conn.execute("DELETE FROM steps WHERE job_id = ? AND idx = ?", (damaged.job_id, damaged.step_idx))
            conn.execute("INSERT OR REPLACE INTO notes (job_id, step_idx, kind, value_json, t_s)"
                         " VALUES (?, ?, ?, ?, ?)",
                         (damaged.job_id, damaged.step_idx, DAMAGED_NOTE, json.dumps(damaged.entry()), time.time()))
        (self.job_dir(damaged.job_id) / damaged.file).unlink(missing_ok=True)

    # ------------------------------------------------------------ events

    @staticmethod
    def _event(conn: sqlite3.Connection, job_id: str | None, kind: str, data: dict, now: float) -> Event:
        cur = conn.execute("INSERT INTO events (job_id, kind, data_json, t_s) VALUES (?, ?, ?, ?)",
                           (job_id, kind, json.dumps(data), now))
        return Event(cur.lastrowid, job_id, kind, data, now)

    def add_event(self, job_id: str | None, kind: str, data: dict, t_s: float | None = None) -> Event:
        """Journal one event (device state, safety, log line) of time ``t_s`` (Unix s; default: now)."""
        with self._tx() as conn:
            return self._event(conn, job_id, kind, data, time.time() if t_s is None else t_s)

    def events(self, after_seq: int = 0, job_id: str | None = None, limit: int = 1000) -> list[Event]:
        """Journaled events with ``seq > after_seq``, oldest first."""
        sql, args = "SELECT * FROM events WHERE seq > ?", [after_seq]
        if job_id is not None:
            sql += " AND job_id = ?"
            args.append(job_id)
        rows = self._conn().execute(sql + " ORDER BY seq LIMIT ?", [*args, limit]).fetchall()
        return [Event(r["seq"], r["job_id"], r["kind"], json.loads(r["data_json"]), r["t_s"]) for r in rows]

    def last_event_seq(self) -> int:
        row = self._conn().execute("SELECT MAX(seq) FROM events").fetchone()
        return int(row[0] or 0)

    # ------------------------------------------------------------ crash recovery

    def committed_scan_files(self) -> set[tuple[str, str]]:
        """``(job id, file relative to its folder)`` of every committed scan."""
        return {(r["job_id"], r["file"]) for r in self._conn().execute("SELECT job_id, file FROM scans")}

    def active_jobs(self) -> list[str]:
        """Ids of the jobs in an active state (running or paused), oldest first."""
        rows = self._conn().execute(
            f"SELECT id FROM jobs WHERE state IN ({','.join('?' * len(ACTIVE_STATES))}) ORDER BY seq",
            sorted(ACTIVE_STATES)).fetchall()
        return [r["id"] for r in rows]


def _job_from_row(row: sqlite3.Row) -> JobRecord:
    return JobRecord(
        id=row["id"], seq=row["seq"], state=row["state"], plan_name=row["plan_name"],
        plan=json.loads(row["plan_json"]), n_steps=row["n_steps"], created_s=row["created_s"],
        updated_s=row["updated_s"], started_s=row["started_s"], finished_s=row["finished_s"],
        progress=row["progress"], current_step=row["current_step"], error=row["error"],
        figures=json.loads(row["figures_json"]), attempts=row["attempts"], idempotency_key=row["idempotency_key"],
    )


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
