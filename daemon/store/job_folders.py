"""The job folders under the state directory: ``jobs/<job id>/`` holds a job's outputs (cloud.ply,
report.json, ...) and ``scans/`` its raw scan files. Writes are durable (temporary name, fsync, rename, fsync of
the folder: :func:`~tandemscan.pipeline.io.durable.write_durably`). See docs/daemon.md.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from tandemscan.daemon.store.rows import PendingScan, StoreError
from tandemscan.pipeline.io.durable import write_durably


def file_sha256(path: Path) -> str:
    """The SHA-256 of the file's bytes (hex)."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


class JobFolders:
    """The ``jobs/`` folder of ``state_dir`` (created when missing)."""

    def __init__(self, state_dir: Path | str):
        self.state_dir = Path(state_dir)
        self.jobs_dir = self.state_dir / "jobs"
        self.jobs_dir.mkdir(parents=True, exist_ok=True)

    def job_dir(self, job_id: str) -> Path:
        """The folder of one job (artifacts and raw scans)."""
        if not job_id or "/" in job_id or job_id.startswith("."):
            raise StoreError(f"invalid job id {job_id!r}")
        return self.jobs_dir / job_id

    def register_scan_file(self, job_id: str, step_idx: int, path: Path, n_points: int) -> PendingScan:
        """A scan file some other writer made durable in the job's folder, to pass to ``commit_step``."""
        path = Path(path)
        if not path.is_file() or self.job_dir(job_id) not in path.parents:
            raise StoreError(f"scan file {path} is not a file in the folder of job {job_id}")
        return PendingScan(step_idx, path, int(n_points), path.stat().st_size, file_sha256(path))

    def write_artifact(self, job_id: str, name: str, data: bytes) -> Path:
        """Write a result file (``cloud.ply``, ``report.json``) durably into the job directory."""
        path = self.job_dir(job_id) / name
        write_durably(path, lambda f: f.write(data))
        return path
