"""The daemon's job runner: :class:`~tandemscan.daemon.runner.JobRunner` on the store's journal.

:class:`StoreJournal` gives the runner the supervisor's motion gate, the manager's pause/cancel/safety
handling and durable step commits; :func:`run_journaled` is the manager's runner. On the simulated cell the
world's state is saved with every commit (before it), so a restarted daemon finds the robots where they were.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from pathlib import Path
from typing import TypeVar

from tandemscan.daemon.jobs import JobContext
from tandemscan.daemon.runner import JobProgress, JobRunner
from tandemscan.daemon.stitcher import ProcessWorldMap
from tandemscan.pipeline import frames as F
from tandemscan.pipeline.plan import Plan
from tandemscan.sim_drivers.persist import save_world_state

log = logging.getLogger(__name__)

T = TypeVar("T")
WORLD_STATE_FILE = "sim_world.json"

# Figures of the report copied onto the job resource (mm, deg, s).
_FIGURE_KEYS = ("scans", "transfers", "points_raw", "points_cloud", "seconds")
_TRUTH_KEYS = ("pose_err_mm_median", "pose_err_mm_max", "pose_err_deg_median", "cloud_rms_mm", "cloud_p95_mm")


class StoreJournal:
    """The :class:`~tandemscan.daemon.runner.StepJournal` of one job in the daemon."""

    def __init__(self, ctx: JobContext):
        self.ctx = ctx
        self.committed = dict(ctx.committed)
        self.world_state_path = ctx.store.state_dir / WORLD_STATE_FILE
        self._progress_tasks: set[asyncio.Task] = set()

    @asynccontextmanager
    async def motion(self, robot: str) -> AsyncIterator[None]:
        async with self.ctx.supervisor.motion(robot):
            yield

    async def run_step(self, idx: int, fn: Callable[[], Awaitable[T]]) -> T:
        return await self.ctx.run_step(idx, fn)

    async def note(self, idx: int, kind: str, value: dict) -> None:
        await asyncio.to_thread(self.ctx.store.note, self.ctx.job.id, idx, kind, value)

    def notes(self, idx: int) -> dict[str, dict]:
        return self.ctx.store.notes(self.ctx.job.id, idx)

    async def commit(self, idx: int, kind: str, result: dict, scan_file: Path | None = None,
                     scan_points: int = 0) -> None:
        await asyncio.to_thread(self._commit, idx, kind, result, scan_file, scan_points)
        self.committed[idx] = result

    def _commit(self, idx: int, kind: str, result: dict, scan_file: Path | None, scan_points: int) -> None:
        store, job_id = self.ctx.store, self.ctx.job.id
        world = getattr(self.ctx.cell, "world", None)
        if world is not None:  # the world first: after a crash it must not be behind the journal
            save_world_state(world, self.world_state_path)
        scan = None if scan_file is None else store.register_scan_file(job_id, idx, scan_file, scan_points)
        poses = {k: result[k] for k in ("T_C_T", "covariance", "joints_rad", "odometry", "T_W_C", "before", "after")
                 if k in result}
        store.commit_step(job_id, idx, kind, result, poses=poses, scan=scan)

    def on_progress(self, p: JobProgress) -> None:
        """The runner's (synchronous) progress callback: journal and publish it in the background."""
        task = asyncio.get_running_loop().create_task(
            self.ctx.progress(min(99.0, 100.0 * p.done / max(p.total, 1)), min(p.done, self.ctx.job.n_steps - 1)))
        self._progress_tasks.add(task)
        task.add_done_callback(self._progress_tasks.discard)

    async def drain(self) -> None:
        await asyncio.gather(*self._progress_tasks, return_exceptions=True)


async def run_journaled(ctx: JobContext) -> dict:
    """Run (or resume) the job of ``ctx`` and return its figures; the cloud and report land in its folder."""
    plan = Plan.model_validate(ctx.job.plan["plan"])
    journal = StoreJournal(ctx)
    job_dir = ctx.store.job_dir(ctx.job.id)
    if ctx.resumed:
        log.info("job %s resumes at step %d of %d", ctx.job.id, min(set(range(len(plan.steps))) - set(ctx.committed),
                                                                      default=len(plan.steps)), len(plan.steps))
    world = getattr(ctx.cell, "world", None)
    if world is not None and ctx.job.attempts == 1:
        # W is the tracker camera frame at the job's first station: a later job on the same simulated cell
        # starts where the previous one left the tracker, and is scored in its own W
        world.T_W_F = F.invert(world.T_F_C())
        await asyncio.to_thread(save_world_state, world, journal.world_state_path)
    worldmap = await asyncio.to_thread(ProcessWorldMap, ctx.config.job.voxel_mm, ctx.config.daemon.worker_niceness)
    runner = JobRunner(ctx.cell, plan, ctx.config, job_dir, journal.on_progress, journal, worldmap)
    try:
        result = await runner.run()
    finally:
        await journal.drain()
        await asyncio.to_thread(worldmap.close)
    # every attempt's resumes, not only this one's (a restart after the last step resumes with nothing to redo)
    resumes = await asyncio.to_thread(ctx.store.notes_of_kind, ctx.job.id, "resume")
    report = dict(result.report) | {"job": ctx.job.id, "resumes": resumes,
                                    "attempts": ctx.store.get_job(ctx.job.id).attempts}
    await asyncio.to_thread(lambda: ctx.store.write_artifact(ctx.job.id, "report.json",
                                                             json.dumps(report, indent=1).encode()))
    figures = {k: report[k] for k in _FIGURE_KEYS if k in report}
    truth = report.get("ground_truth") or {}
    figures |= {k: truth[k] for k in _TRUTH_KEYS if k in truth}
    return figures
