"""The job manager: a queue that runs one job at a time, its state machine, and crash resumption.

States: ``queued -> running -> succeeded | failed | cancelled``; ``running <-> paused`` (operator, at
the next step boundary); ``running -> paused_safety`` (a safety stop, at once) and back by ``resume`` once
the safety latch can be reset. A paused job keeps the cell: queued jobs wait behind it.

On start the manager asks the store for jobs that were active when the daemon stopped: a ``running`` job
is resumed by the runner from its first uncommitted step; a paused one stays paused.

The runner is ``async runner(ctx: JobContext) -> dict`` (figures of the finished job). It calls
``ctx.run_step(i, kind, fn)`` for each step not yet committed and ``ctx.progress(...)`` as it goes.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

from tandemscan.daemon.events import EventBus
from tandemscan.daemon.store import FINAL_STATES, Event, JobRecord, JobStore, StoreError
from tandemscan.daemon.supervisor import Supervisor
from tandemscan.drivers.errors import SafetyStop
from tandemscan.drivers.tasks import cancel_and_wait

log = logging.getLogger(__name__)


class JobError(Exception):
    """A job request cannot be done now (unknown job, wrong state); ``status`` is the HTTP status."""

    def __init__(self, message: str, status: int = 409):
        super().__init__(message)
        self.status = status


class JobCancelled(Exception):
    """Raised inside a runner when its job was cancelled."""


@dataclass
class JobContext:
    """What a runner gets: the job, the journal, the devices' supervisor, the cell session (its motion gate and
    observers, :mod:`tandemscan.daemon.session`) and pause/cancel checkpoints."""

    job: JobRecord
    store: JobStore
    supervisor: Supervisor
    manager: JobManager
    cell: Any = None
    config: Any = None
    committed: dict[int, dict] = field(default_factory=dict)
    session: Any = None

    @property
    def resumed(self) -> bool:
        """True when this run continues a job that committed steps before (a restart or a crash)."""
        return bool(self.committed)

    async def checkpoint(self) -> None:
        """Wait while the job is paused; raise :class:`JobCancelled` once it is cancelled."""
        await self.manager._checkpoint(self.job.id)

    async def run_step(self, idx: int, fn: Callable[[], Awaitable[Any]]) -> Any:
        """Run one step: wait at the checkpoint, and after a safety stop pause and run it again on resume."""
        while True:
            await self.checkpoint()
            try:
                return await fn()
            except SafetyStop as e:
                log.warning("job %s step %d halted by safety stop: %s", self.job.id, idx, e)
                await self.manager._safety_pause(self.job.id, str(e))

    async def progress(self, percent: float, current_step: int | None, figures: dict | None = None) -> None:
        """Publish progress (0-100), the step under way and optional figures so far."""
        ev = await asyncio.to_thread(self.store.set_progress, self.job.id, percent, current_step, figures)
        self.manager.bus.publish(ev)


Runner = Callable[[JobContext], Awaitable[dict]]


def request_hash(body: dict) -> str:
    """Canonical hash of a request body, to tell a retry from a different request under one key."""
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


@dataclass(eq=False)
class JobManager:
    """Queue and state machine of jobs; runs one at a time through ``runner`` on ``cell``."""

    store: JobStore
    bus: EventBus
    supervisor: Supervisor
    runner: Runner
    cell: Any = None
    config: Any = None
    session: Any = None
    active_id: str | None = None
    _wake: asyncio.Event = field(default_factory=asyncio.Event)
    _resume: dict[str, asyncio.Event] = field(default_factory=dict)
    _cancelled: set[str] = field(default_factory=set)
    _run_task: asyncio.Task | None = None
    _scheduler: asyncio.Task | None = None

    def __post_init__(self) -> None:
        self.supervisor.safety_listeners.append(self._on_safety_stop)

    # ------------------------------------------------------------ lifecycle

    async def start(self) -> None:
        """Recover after a restart and start the scheduler."""
        active = await asyncio.to_thread(self.store.recover)
        if active:
            self.active_id = active[0]
            for extra in active[1:]:  # only one job can have held the cell; others go back to the queue
                await self._set_state(extra, "queued")
            log.info("resuming job %s", self.active_id)
        self._scheduler = asyncio.create_task(self._schedule(), name="job-scheduler")
        self._wake.set()

    async def close(self) -> None:
        """Stop scheduling; a job under way is interrupted and stays resumable (state kept)."""
        await cancel_and_wait(self._scheduler, self._run_task)

    # ------------------------------------------------------------ requests

    async def submit(self, plan_name: str, plan: dict, n_steps: int, idempotency_key: str | None,
                     body_hash: str | None) -> tuple[JobRecord, bool]:
        """Queue a job; returns ``(job, created)`` (``created`` False for a retry under the same key)."""
        job, event = await asyncio.to_thread(
            self.store.create_job, plan_name, plan, n_steps, idempotency_key, body_hash)
        if event is not None:
            self.bus.publish(event)
            self._wake.set()
        return job, event is not None

    def get(self, job_id: str) -> JobRecord:
        try:
            return self.store.get_job(job_id)
        except StoreError as e:
            raise JobError(str(e), 404) from e

    async def cancel(self, job_id: str) -> JobRecord:
        job = self.get(job_id)
        if job.state in FINAL_STATES:
            raise JobError(f"job {job_id} is already {job.state}")
        if job.state == "queued":
            return await self._set_state(job_id, "cancelled")
        self._cancelled.add(job_id)
        self._resume_event(job_id).set()
        if self._run_task is not None and self.active_id == job_id:
            # a long retry period: the run task's own clean-up (halt, state change) must not be interrupted
            await cancel_and_wait(self._run_task, retry_s=10.0)
        else:  # an active job whose runner is not up (recovered paused job)
            await self._finish(job_id, "cancelled")
        return self.get(job_id)

    async def pause(self, job_id: str) -> JobRecord:
        job = self.get(job_id)
        if job.state != "running":
            raise JobError(f"job {job_id} is {job.state}; only a running job can be paused")
        self._resume_event(job_id).clear()
        return await self._set_state(job_id, "paused")

    async def resume(self, job_id: str) -> JobRecord:
        job = self.get(job_id)
        if job.state not in ("paused", "paused_safety"):
            raise JobError(f"job {job_id} is {job.state}; only a paused job can be resumed")
        if job.state == "paused_safety" or self.supervisor.latched_reason is not None:
            try:
                await self.supervisor.reset_safety()
            except SafetyStop as e:
                raise JobError(f"cannot resume: {e.reason}") from e
        job = await self._set_state(job_id, "running")
        self._resume_event(job_id).set()
        self._wake.set()
        return job

    # ------------------------------------------------------------ runner side

    def _resume_event(self, job_id: str) -> asyncio.Event:
        if job_id not in self._resume:
            self._resume[job_id] = asyncio.Event()
            self._resume[job_id].set()
        return self._resume[job_id]

    async def _checkpoint(self, job_id: str) -> None:
        while True:
            if job_id in self._cancelled:
                raise JobCancelled(job_id)
            if self.store.get_job(job_id).state == "running":
                return
            ev = self._resume_event(job_id)
            ev.clear()
            await ev.wait()

    async def _safety_pause(self, job_id: str, reason: str) -> None:
        if self.store.get_job(job_id).state == "running":
            await self._set_state(job_id, "paused_safety", error=reason)

    def _on_safety_stop(self, reason: str) -> None:
        if self.active_id is not None and self.store.get_job(self.active_id).state == "running":
            asyncio.get_running_loop().create_task(self._safety_pause(self.active_id, reason))

    # ------------------------------------------------------------ scheduling

    async def _schedule(self) -> None:
        while True:
            await self._wake.wait()
            self._wake.clear()
            if self.active_id is None:
                nxt = self.store.next_queued()
                if nxt is None:
                    continue
                self.active_id = nxt.id
            job = self.store.get_job(self.active_id)
            if job.state in ("paused", "paused_safety") and self._run_task is None:
                # recovered paused job: start its runner, which waits at its first checkpoint
                self._resume_event(job.id).clear()
            elif job.state == "queued":
                job = await self._set_state(job.id, "running")
            if self._run_task is None:
                self._run_task = asyncio.create_task(self._run(job.id), name=f"job-{job.id}")

    async def _run(self, job_id: str) -> None:
        try:
            job = await asyncio.to_thread(self.store.begin_attempt, job_id)
            committed = await asyncio.to_thread(self.store.committed_steps, job_id)
            ctx = JobContext(job, self.store, self.supervisor, self, self.cell, self.config, committed, self.session)
            figures = await self.runner(ctx)
        except (JobCancelled, asyncio.CancelledError):
            if job_id in self._cancelled:
                await self.supervisor.halt()
                await self._finish(job_id, "cancelled")
            else:  # daemon shutting down: the job stays active and resumes on the next start
                log.info("job %s interrupted by shutdown; it resumes on restart", job_id)
                self._run_task = None
                raise
        except Exception as e:
            log.exception("job %s failed", job_id)
            await self._finish(job_id, "failed", f"{type(e).__name__}: {e}")
        else:
            ev = await asyncio.to_thread(self.store.set_progress, job_id, 100.0, None, figures)
            self.bus.publish(ev)
            await self._finish(job_id, "succeeded")

    async def _finish(self, job_id: str, state: str, error: str | None = None) -> None:
        await self._set_state(job_id, state, error)
        self._cancelled.discard(job_id)
        self._resume.pop(job_id, None)
        if self.active_id == job_id:
            self.active_id = None
        self._run_task = None
        self._wake.set()

    async def _set_state(self, job_id: str, state: str, error: str | None = None) -> JobRecord:
        job, event = await asyncio.to_thread(self.store.set_state, job_id, state, error)
        self.bus.publish(event)
        return job

    def publish(self, kind: str, data: dict, job_id: str | None = None) -> Event:
        """Journal and publish a non-job event (device, safety)."""
        ev = self.store.add_event(job_id, kind, data)
        self.bus.publish(ev)
        return ev
