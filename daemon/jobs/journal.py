"""The daemon's job runner: :class:`~tandemscan.daemon.jobs.runner.JobRunner` on the store's journal.

:class:`StoreJournal` gives the runner the manager's pause/cancel/safety handling and durable step commits;
the motion gate is the daemon's cell session's (:mod:`tandemscan.daemon.cell.session`), not the journal's.
:func:`run_journaled` is the manager's runner. The simulated world keeps its own state (its twins save it as
they act), so the journal never touches it.
"""

from __future__ import annotations

import asyncio
import logging
import shutil
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import TypeVar

from tandemscan.config.models import CellConfig
from tandemscan.daemon.cell.session import CellSession
from tandemscan.daemon.jobs.context import JobContext
from tandemscan.daemon.jobs.coordinate_transfer import return_from_transfer
from tandemscan.daemon.jobs.runner import JobProgress, JobRunner
from tandemscan.daemon.jobs.stitcher import ProcessWorldMap
from tandemscan.daemon.store.job_store import JobRecord, JobStore
from tandemscan.daemon.store.part_results import prepare_part, record_part
from tandemscan.pipeline.io.raw_scan import remove_thinned_copies
from tandemscan.pipeline.job_report import JobHistory
from tandemscan.pipeline.planning.plan import Plan
from tandemscan.pipeline.registration.correction import remove_joint_folder
from tandemscan.pipeline.stitching.tiles import TILES_FOLDER

log = logging.getLogger(__name__)

T = TypeVar("T")

# Figures of the report copied onto the job resource (mm, deg, s).
_FIGURE_KEYS = ("scans", "transfers", "points_raw", "points_cloud", "seconds")
_TRUTH_KEYS = ("pose_err_mm_median", "pose_err_mm_max", "pose_err_deg_median", "cloud_rms_mm", "cloud_p95_mm")


class StoreJournal:
    """The :class:`~tandemscan.daemon.jobs.step_journal.StepJournal` of one job in the daemon."""

    def __init__(self, ctx: JobContext):
        self.ctx = ctx
        self.committed = dict(ctx.committed)
        self._progress_tasks: set[asyncio.Task] = set()

    async def run_step(self, idx: int, fn: Callable[[], Awaitable[T]]) -> T:
        return await self.ctx.run_step(idx, fn)

    async def note(self, idx: int, kind: str, value: dict) -> None:
        await asyncio.to_thread(self.ctx.store.note, self.ctx.job.id, idx, kind, value)

    def notes(self, idx: int) -> dict[str, dict]:
        return self.ctx.store.notes(self.ctx.job.id, idx)

    async def record_resume(self, idx: int, entry: dict) -> None:
        await asyncio.to_thread(self.ctx.store.add_resume, self.ctx.job.id, self.ctx.job.attempts, idx, entry)

    async def commit(self, idx: int, kind: str, result: dict, scan_file: Path | None = None,
                     scan_points: int = 0) -> None:
        await asyncio.to_thread(self._commit, idx, kind, result, scan_file, scan_points)
        self.committed[idx] = result

    def _commit(self, idx: int, kind: str, result: dict, scan_file: Path | None, scan_points: int) -> None:
        store, job_id = self.ctx.store, self.ctx.job.id
        scan = None if scan_file is None else store.register_scan_file(job_id, idx, scan_file, scan_points)
        store.commit_step(job_id, idx, kind, result, scan=scan)

    async def history(self) -> JobHistory:
        """Every resume of every attempt of the job, not only this one's (a restart after the last step resumes
        with nothing to redo), and its attempts: the report's ``resumes`` and ``attempts``."""
        store, job_id = self.ctx.store, self.ctx.job.id
        resumes = await asyncio.to_thread(store.resumes, job_id)
        attempts = (await asyncio.to_thread(store.get_job, job_id)).attempts
        return JobHistory(tuple(resumes), attempts)

    def on_progress(self, p: JobProgress) -> None:
        """The runner's (synchronous) progress callback: journal and publish it in the background."""
        task = asyncio.get_running_loop().create_task(
            self.ctx.progress(min(99.0, 100.0 * p.done / max(p.total, 1)), min(p.done, self.ctx.job.n_steps - 1)))
        self._progress_tasks.add(task)
        task.add_done_callback(self._progress_tasks.discard)

    async def drain(self) -> None:
        await asyncio.gather(*self._progress_tasks, return_exceptions=True)


def close_map(worldmap: ProcessWorldMap, job_dir: Path, scan_store: Path) -> None:
    """Stop the job's map process (``ProcessWorldMap.close``: work under way there abandoned, its own clean-up with
    it) and remove the scratch files that work leaves where the job ends before its end ran to completion
    (cancelled, failed, or interrupted by the daemon's stop; a resumed job makes them again):
    :func:`remove_scratch`, among them a thinned copy the map's process wrote after the runner removed them (a scan
    merged as the job was cancelled). A job that ran to its end removed them itself."""
    worldmap.close()
    remove_scratch(job_dir, scan_store)


def remove_scratch(job_dir: Path, scan_store: Path) -> None:
    """Remove a job's scratch files: in ``scan_store`` its scans prepared for the joint refinement
    (``correction.remove_joint_folder``) and its tiles' files and shards (``tiles.TILES_FOLDER``), and in
    ``job_dir`` the scans' thinned copies (``raw_scan.remove_thinned_copies``)."""
    remove_joint_folder(scan_store)
    shutil.rmtree(Path(scan_store) / TILES_FOLDER, ignore_errors=True)
    remove_thinned_copies(job_dir)


async def run_journaled(ctx: JobContext) -> dict:
    """Run (or resume) the job of ``ctx`` and return its figures; the cloud and report land in its folder."""
    plan = Plan.model_validate(ctx.job.plan["plan"])
    journal = StoreJournal(ctx)
    job_dir = ctx.store.job_dir(ctx.job.id)
    if ctx.resumed:
        log.info("job %s resumes at step %d of %d", ctx.job.id, min(set(range(len(plan.steps))) - set(ctx.committed),
                                                                      default=len(plan.steps)), len(plan.steps))
    worldmap = await asyncio.to_thread(ProcessWorldMap, ctx.config.job.voxel_mm, ctx.config.daemon.worker_niceness,
                                     ctx.config.compute.reads_scan_store)
    config = await asyncio.to_thread(prepare_part, ctx.config, ctx.job.plan, job_dir, ctx.store.state_dir)
    runner = JobRunner(ctx.session, plan, config, job_dir, journal.on_progress, journal, worldmap,
                       ctx.config.job.max_scans_left_out, journal.history)
    try:
        result = await runner.run()
    finally:
        await journal.drain()
        await asyncio.to_thread(close_map, worldmap, job_dir, ctx.config.compute.store_of(job_dir))
    report = result.report  # report.json, written once by the end of the job
    await asyncio.to_thread(record_part, ctx.store.state_dir, ctx.job.id, report)
    figures = {k: report[k] for k in _FIGURE_KEYS if k in report} | {"scans_left_out": len(report["scans_left_out"])}
    truth = report.get("ground_truth") or {}
    figures |= {k: truth[k] for k in _TRUTH_KEYS if k in truth}
    return figures


def journaled_abandon(session: CellSession, config: CellConfig):
    """The manager's ``abandon`` for the daemon: a failed or cancelled job's half transfer undone
    (:func:`~tandemscan.daemon.jobs.coordinate_transfer.return_from_transfer`) from its journal, then its scratch
    files removed (:func:`remove_scratch`: a job cancelled after a crash without its runner up again leaves those of
    the attempt the crash ended; where the runner ran, its :func:`close_map` removed them already)."""

    async def abandon(job: JobRecord, store: JobStore) -> None:
        plan = Plan.model_validate(job.plan["plan"])
        try:
            committed = set(await asyncio.to_thread(store.committed_steps, job.id))
            await return_from_transfer(session, plan, committed, lambda i: store.notes(job.id, i), config)
        finally:
            job_dir = store.job_dir(job.id)
            await asyncio.to_thread(remove_scratch, job_dir, config.compute.store_of(job_dir))

    return abandon

