"""The job manager: a queue that runs one job at a time, its state machine, and crash resumption.

States: ``queued -> running -> succeeded | failed | cancelled``; ``running <-> paused`` (operator, at
the next step boundary); ``running -> paused_safety`` (a safety stop, at once) and back by ``resume`` once
the safety latch can be reset; ``running -> paused_fault`` (a recoverable device or storage fault,
:mod:`tandemscan.daemon.jobs.faults`: motion halted, the runner ended) and back by ``resume`` (the operator, or the
retry policy ``[daemon] fault_retry_*`` for device faults once every device is up), which starts a new attempt
from the committed steps. A paused job keeps the cell: queued jobs wait behind it. A queued job waits, with the
reason in its ``error``, while a device is down. A failed or cancelled job first brings the cell back to a known
state (``abandon``: no tracker left mid-transfer).

A state change the journal cannot take (a full disk) is held in memory (:mod:`tandemscan.daemon.jobs.held_states`).

On start the manager asks the store for jobs that were active when the daemon stopped: a ``running`` job
is resumed by the runner from its first uncommitted step; a paused one stays paused.

The runner and what it gets: :mod:`tandemscan.daemon.jobs.context`.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import logging
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from tandemscan.daemon.cell.supervisor import Supervisor, backoff_delays
from tandemscan.daemon.job_state import FINAL_STATES, PAUSED_STATES, JobState
from tandemscan.daemon.jobs.context import Abandon, JobCancelled, JobContext, Runner
from tandemscan.daemon.jobs.faults import JobFault, classify_fault
from tandemscan.daemon.jobs.held_states import HeldStates
from tandemscan.daemon.store.events import EventBus
from tandemscan.daemon.store.job_store import STORAGE_ERRORS, DamagedScan, JobRecord, JobStore, StoreError, recover
from tandemscan.drivers.errors import SafetyStop
from tandemscan.drivers.tasks import cancel_and_wait

log = logging.getLogger(__name__)


class JobRequestError(Exception):
    """A job request cannot be done now (unknown job, wrong state); ``status`` is the HTTP status."""

    def __init__(self, message: str, status: int = 409):
        super().__init__(message)
        self.status = status


@dataclass(frozen=True)
class RetryPolicy:
    """Automatic resumes of a job paused by a device fault: ``attempts`` since its last committed step, the first
    after ``initial_s``, doubling to ``max_s`` (seconds)."""

    attempts: int = 3
    initial_s: float = 2.0
    max_s: float = 60.0

    def delay_s(self, attempt: int) -> float:
        """The wait before automatic resume ``attempt`` (1-based), without jitter."""
        delays = backoff_delays(self.initial_s, self.max_s, jitter=0.0)
        return [next(delays) for _ in range(attempt)][-1]


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
    retry: RetryPolicy = RetryPolicy()
    abandon: Abandon | None = None
    active_id: str | None = None
    _wake: asyncio.Event = field(default_factory=asyncio.Event)
    _resume: dict[str, asyncio.Event] = field(default_factory=dict)
    _cancelled: set[str] = field(default_factory=set)
    _run_task: asyncio.Task | None = None
    _scheduler: asyncio.Task | None = None
    _retry_task: asyncio.Task | None = None
    _retries: dict[str, tuple[int, int]] = field(default_factory=dict)  # job: (retries, steps done at the last)
    _held: HeldStates = field(init=False)  # state changes the journal refused, written once it takes them
    damaged_scans: deque[DamagedScan] = field(default_factory=lambda: deque(maxlen=20))  # found since the start

    def __post_init__(self) -> None:
        self._held = HeldStates(self.store, self.bus)
        self.supervisor.safety_listeners.append(self._on_safety_stop)
        self.supervisor.connection_listeners.append(lambda whole: self._wake.set())

    # ------------------------------------------------------------ lifecycle

    async def start(self) -> None:
        """Recover after a restart and start the scheduler."""
        active = await asyncio.to_thread(recover, self.store)
        if active:
            self.active_id = active[0]
            for extra in active[1:]:  # only one job can have held the cell; others go back to the queue
                await self._set_state(extra, JobState.QUEUED)
            log.info("resuming job %s", self.active_id)
        self._scheduler = asyncio.create_task(self._schedule(), name="job-scheduler")
        self._wake.set()

    async def close(self) -> None:
        """Stop scheduling; a job under way is interrupted and stays resumable (state kept)."""
        await cancel_and_wait(self._scheduler, self._run_task, self._retry_task)
        await self._held.close()

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
        """The job as the manager knows it (a state change the journal could not take yet included)."""
        try:
            return self.current(self.store.get_job(job_id))
        except StoreError as e:
            raise JobRequestError(str(e), 404) from e

    async def read(self, job_id: str) -> JobRecord:
        """:meth:`get` in a worker thread: the manager's own reads keep SQLite off the event loop."""
        return await asyncio.to_thread(self.get, job_id)

    def current(self, job: JobRecord) -> JobRecord:
        """``job`` (read from the store) with a state change held in memory applied."""
        return self._held.current(job)

    @property
    def storage_error(self) -> str | None:
        """Why a state change is held in memory now (the journal refuses writes); None when all are written."""
        return self._held.error

    async def cancel(self, job_id: str) -> JobRecord:
        job = await self.read(job_id)
        if job.state in FINAL_STATES:
            raise JobRequestError(f"job {job_id} is already {job.state}")
        if job.state == JobState.QUEUED:
            return await self._set_state(job_id, JobState.CANCELLED)
        await cancel_and_wait(self._retry_task)
        self._cancelled.add(job_id)
        self._resume_event(job_id).set()
        if self._run_task is not None and self.active_id == job_id:
            # a long retry period: the run task's own clean-up (halt, state change) must not be interrupted
            await cancel_and_wait(self._run_task, retry_s=10.0)
        else:  # an active job whose runner is not up (recovered paused job, a job paused by a fault)
            await self._abandon(job_id)
            await self._finish(job_id, JobState.CANCELLED)
        return await self.read(job_id)

    async def pause(self, job_id: str) -> JobRecord:
        job = await self.read(job_id)
        if job.state != JobState.RUNNING:
            raise JobRequestError(f"job {job_id} is {job.state}; only a running job can be paused")
        self._resume_event(job_id).clear()
        return await self._set_state(job_id, JobState.PAUSED)

    async def resume(self, job_id: str) -> JobRecord:
        """Resume a paused job; one paused by a fault starts a new attempt at the step that faulted."""
        job = await self.read(job_id)
        if job.state not in PAUSED_STATES:
            raise JobRequestError(f"job {job_id} is {job.state}; only a paused job can be resumed")
        down = self.supervisor.down_devices()
        if job.state == JobState.PAUSED_FAULT and down:
            raise JobRequestError(f"cannot resume: devices down: {', '.join(down)} (the job resumes once they are up)")
        if self._retry_task is not None and self._retry_task is not asyncio.current_task():
            await cancel_and_wait(self._retry_task)  # the operator resumes before the retry policy does
        self._retry_task = None
        if job.state == JobState.PAUSED_SAFETY or self.supervisor.latched_reason is not None:
            try:
                await self.supervisor.reset_safety()
            except SafetyStop as e:
                raise JobRequestError(f"cannot resume: {e.reason}") from e
        job = await self._set_state(job_id, JobState.RUNNING)
        self._resume_event(job_id).set()
        self._wake.set()
        return job

    # ------------------------------------------------------------ runner side

    def _resume_event(self, job_id: str) -> asyncio.Event:
        if job_id not in self._resume:
            self._resume[job_id] = asyncio.Event()
            self._resume[job_id].set()
        return self._resume[job_id]

    async def checkpoint(self, job_id: str) -> None:
        """Wait while the job is paused; raise :class:`JobCancelled` once it is cancelled (a runner's
        checkpoint, :class:`~tandemscan.daemon.jobs.context.JobControl`)."""
        while True:
            if job_id in self._cancelled:
                raise JobCancelled(job_id)
            if (await self.read(job_id)).state == JobState.RUNNING:
                return
            ev = self._resume_event(job_id)
            ev.clear()
            await ev.wait()

    async def safety_pause(self, job_id: str, reason: str) -> None:
        """Pause the job, while it runs, after a safety stop (``reason``)."""
        if (await self.read(job_id)).state == JobState.RUNNING:
            await self._set_state(job_id, JobState.PAUSED_SAFETY, error=reason)

    def _on_safety_stop(self, reason: str) -> None:
        if self.active_id is not None:  # safety_pause pauses it if it is running
            asyncio.get_running_loop().create_task(self.safety_pause(self.active_id, reason))

    # ------------------------------------------------------------ scheduling

    async def _schedule(self) -> None:
        while True:
            await self._wake.wait()
            self._wake.clear()
            if self.active_id is None:
                nxt = await asyncio.to_thread(self.store.next_queued)
                if nxt is None or await self._waits_for_cell(nxt):
                    continue
                self.active_id = nxt.id
            job = await self.read(self.active_id)
            if job.state == JobState.PAUSED_FAULT:
                continue  # no runner until it is resumed
            if job.state in PAUSED_STATES and self._run_task is None:
                # recovered paused job: start its runner, which waits at its first checkpoint
                self._resume_event(job.id).clear()
            elif job.state == JobState.QUEUED:
                job = await self._set_state(job.id, JobState.RUNNING)
            if self._run_task is None:
                self._run_task = asyncio.create_task(self._run(job.id), name=f"job-{job.id}")

    async def _waits_for_cell(self, job: JobRecord) -> bool:
        """Whether the queued ``job`` must wait because a device is down; its ``error`` says which."""
        down = self.supervisor.down_devices()
        if not down:
            return False
        reason = f"waiting for the cell: devices down: {', '.join(down)}"
        if job.error != reason:
            await self._set_state(job.id, JobState.QUEUED, reason)
        return True

    async def _run(self, job_id: str) -> None:
        try:
            job = await asyncio.to_thread(self.store.begin_attempt, job_id)
            await self._take_back_damaged_scans(job_id)
            committed = await asyncio.to_thread(self.store.committed_steps, job_id)
            ctx = JobContext(job, self.store, self.supervisor, self, self.cell, self.config, committed, self.session)
            figures = await self.runner(ctx)
            ev = await asyncio.to_thread(self.store.set_progress, job_id, 100.0, None, figures)
            gaps = await asyncio.to_thread(self._gaps, job)
        except (JobCancelled, asyncio.CancelledError):
            if job_id in self._cancelled:
                task = asyncio.current_task()
                while task.uncancel():  # the clean-up below moves the tracking robot: it must not be cut short
                    pass
                await self.supervisor.halt()
                await self._abandon(job_id)
                await self._finish(job_id, JobState.CANCELLED)
            else:  # daemon shutting down: the job stays active and resumes on the next start
                log.info("job %s interrupted by shutdown; it resumes on restart", job_id)
                self._run_task = None
                raise
        except Exception as e:
            fault = classify_fault(e)
            if fault is None:
                log.exception("job %s failed", job_id)
                await self.supervisor.halt()
                await self._abandon(job_id)
                await self._finish(job_id, JobState.FAILED, f"{type(e).__name__}: {e}")
            else:
                await self._fault_pause(job_id, fault)
        else:
            self.bus.publish(ev)
            await self._finish(job_id, JobState.SUCCEEDED if gaps is None else JobState.SUCCEEDED_WITH_GAPS, gaps)

    def _gaps(self, job: JobRecord) -> str | None:
        """(thread) What a finished job left out: the scans whose target the tracker could not see, from its
        journal (``{"untracked": ...}`` step results), as one line; None when it left out none."""
        left_out = [r["untracked"] for r in self.store.committed_steps(job.id).values() if r and "untracked" in r]
        if not left_out:
            return None
        planned = sum(s.get("kind") == "scan" for s in job.plan.get("plan", {}).get("steps", []))
        listed = "; ".join(f"step {e['step']} ({e['label']}): {e['reason']}" for e in left_out[:3])
        more = f"; and {len(left_out) - 3} more" if len(left_out) > 3 else ""
        return f"{len(left_out)} of {planned} scans left out, the tracker could not see the target: {listed}{more}"

    async def _take_back_damaged_scans(self, job_id: str) -> None:
        """Before a run reuses the job's committed scans: each whose file is missing or not what was committed (its
        size, its SHA-256) is named (log, a ``scan_damaged`` event, ``damaged_scans``) and its step taken back out
        of the journal, so that the runner measures it again."""
        for damaged in await asyncio.to_thread(self.store.damaged_scans, job_id):
            log.error("job %s: scan %s of step %d (%s) is damaged: %s; its step is measured again", job_id,
                      damaged.index, damaged.step_idx, damaged.file, damaged.reason)
            await asyncio.to_thread(self.store.uncommit_damaged_scan, damaged)
            self.damaged_scans.append(damaged)
            self.bus.publish(await asyncio.to_thread(self.store.add_event, job_id, "scan_damaged", damaged.entry()))

    async def _fault_pause(self, job_id: str, fault: JobFault) -> None:
        """A recoverable fault: motion halted, the job ``paused_fault`` with the reason, its runner ended; a device
        fault is resumed by the retry policy while it has attempts left."""
        await self.supervisor.halt()
        retries, done_before = self._retries.get(job_id, (0, -1))
        done = await asyncio.to_thread(self.store.steps_done, job_id)
        retries = 0 if done != done_before else retries  # a committed step since the last fault: a fresh budget
        auto = fault.kind == "device" and retries < self.retry.attempts
        plan = (f"; automatic resume {retries + 1} of {self.retry.attempts} in {self.retry.delay_s(retries + 1):.1f} s "
                "once every device is up") if auto else ("; resume to retry" if fault.kind == "device" else "")
        log.warning("job %s paused at step %d: %s", job_id, done, fault.reason)
        await self._set_state(job_id, JobState.PAUSED_FAULT, fault.reason + plan)
        self._retries[job_id] = (retries + 1 if auto else retries, done)
        self._run_task = None
        if auto:
            self._retry_task = asyncio.create_task(self._resume_later(job_id, self.retry.delay_s(retries + 1)),
                                                   name=f"retry-{job_id}")

    async def _resume_later(self, job_id: str, delay_s: float) -> None:
        """The retry policy: after ``delay_s``, once every device is up and no safety stop is latched, resume."""
        await asyncio.sleep(delay_s)
        while self.supervisor.down_devices() or self.supervisor.latched_reason is not None:
            await asyncio.sleep(self.supervisor.health_period_s)
        if (await self.read(job_id)).state == JobState.PAUSED_FAULT:
            log.info("job %s: automatic resume after a device fault", job_id)
            await self.resume(job_id)

    async def _abandon(self, job_id: str) -> None:
        """Bring the cell back to a known state after ``job_id`` failed or was cancelled; a failure is logged."""
        if self.abandon is None:
            return
        try:
            await self.abandon(await self.read(job_id), self.store)
        except Exception:
            log.exception("job %s: the cell could not be brought back to a known state", job_id)

    async def _finish(self, job_id: str, state: str, error: str | None = None) -> None:
        await self._set_state(job_id, state, error)
        self._cancelled.discard(job_id)
        self._resume.pop(job_id, None)
        self._retries.pop(job_id, None)
        if self.active_id == job_id:
            self.active_id = None
        self._run_task = None
        self._wake.set()

    async def _set_state(self, job_id: str, state: str, error: str | None = None) -> JobRecord:
        """Journal a state change and publish it; one the journal cannot take is held and retried."""
        try:
            job, event = await asyncio.to_thread(self.store.set_state, job_id, state, error)
        except STORAGE_ERRORS as e:
            log.error("job %s: state %s held in memory, the journal refuses it: %s", job_id, state, e)
            self._held.hold(job_id, state, error)
            return await self.read(job_id)
        self._held.written(job_id)
        self.bus.publish(event)
        return job
