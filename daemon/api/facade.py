"""The daemon as the REST API sees it: one coroutine per question or command, none of which blocks the event loop.

The routers (``daemon/api/routers/``) are a thin HTTP gateway over this facade, as bluesky-queueserver keeps its
manager apart from its HTTP server: they parse requests and shape answers, the facade reads the journal and
commands the job manager and the supervisor. Every read of the journal runs in the facade's one store thread (a
dedicated executor thread with its own SQLite connection, so SQLite's work and the JSON decoding of rows never
run on the loop); file reads (plans, the calibration file, a job's report) and disk usage run in asyncio's
default thread pool; commands are coroutines of the manager and the supervisor on the loop. Refusals are
:class:`~tandemscan.daemon.api.errors.ApiProblem` with their HTTP status. See docs/daemon.md.
"""

from __future__ import annotations

import asyncio
import functools
import logging
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, TypeVar

import numpy as np
from fastapi import Depends, Request
from prometheus_client import generate_latest
from tandemscan.daemon.api.errors import ApiProblem
from tandemscan.daemon.api.models import Job, JobPage, JobRequest, job_body
from tandemscan.daemon.calibration.current import InstallationError, installation_for_job, resolve_installation
from tandemscan.daemon.calibration.verify import last_verification
from tandemscan.daemon.job_state import FINAL_STATES
from tandemscan.daemon.jobs.manager import request_hash
from tandemscan.daemon.store.events import Subscription, sse_text
from tandemscan.daemon.store.job_store import IdempotencyConflict, JobRecord
from tandemscan.drivers.errors import SafetyStop
from tandemscan.drivers.interfaces import SafetyState
from tandemscan.pipeline.planning.plan import Plan, PlanError

if TYPE_CHECKING:
    from tandemscan.daemon.service import Daemon

log = logging.getLogger(__name__)
T = TypeVar("T")
#: the installation transforms ``GET /v1/calibration`` reports (4x4, mm)
CALIBRATION_TRANSFORMS = ("T_V1_C", "T_V2_B", "T_E_S", "T_T_S")
#: most journaled events one reconnecting event stream replays
MAX_REPLAYED_EVENTS = 10000


class ServiceFacade:
    """Async view of one :class:`~tandemscan.daemon.service.Daemon` for the REST routers."""

    def __init__(self, daemon: Daemon):
        self.daemon = daemon
        self._store_thread = ThreadPoolExecutor(max_workers=1, thread_name_prefix="store-reads")

    @property
    def token(self) -> str | None:
        return self.daemon.token

    @property
    def version(self) -> str:
        return self.daemon.version

    def close(self) -> None:
        """Let the store thread go (reads still queued are dropped)."""
        self._store_thread.shutdown(wait=False, cancel_futures=True)

    async def read(self, fn: Callable[..., T], /, *args) -> T:
        """``fn(*args)`` in the store thread: how every read of the journal leaves the event loop."""
        return await asyncio.get_running_loop().run_in_executor(self._store_thread, functools.partial(fn, *args))

    # ------------------------------------------------------------ jobs

    def _body(self, job: JobRecord) -> Job:
        """(store thread) The wire form of ``job``, its committed steps counted."""
        return job_body(job, self.daemon.store.steps_done(job.id))

    async def job_record(self, job_id: str) -> JobRecord:
        """The job as the manager knows it; 404 (:class:`~tandemscan.daemon.jobs.manager.JobRequestError`) when
        unknown."""
        return await self.read(self.daemon.manager.get, job_id)

    async def job_json(self, job_id: str) -> bytes:
        """The job's JSON (a :class:`~tandemscan.daemon.api.models.Job`), read and encoded in the store thread."""
        return await self.read(lambda: self._body(self.daemon.manager.get(job_id)).model_dump_json().encode())

    async def jobs_json(self, states: list[str] | None, plan: str | None, limit: int, offset: int,
                        next_url: Callable[[int], str]) -> bytes:
        """One page of jobs, newest first, as the JSON of a :class:`~tandemscan.daemon.api.models.JobPage` (read
        and encoded in the store thread); ``next_url(offset)`` links the next page when there is one."""
        def page() -> bytes:
            jobs, total = self.daemon.store.list_jobs(states, plan, None, limit, offset)
            items = [self._body(self.daemon.manager.current(j)) for j in jobs]
            nxt = next_url(offset + len(items)) if offset + len(items) < total else None
            return JobPage(items=items, total=total, limit=limit, offset=offset, next=nxt).model_dump_json().encode()

        return await self.read(page)

    async def submit(self, req: JobRequest, idempotency_key: str | None) -> tuple[Job, bool]:
        """Queue a job: ``(job, created)``; 404 unknown plan, 409 invalid plan or key reused, 507 no room."""
        name, plan = await asyncio.to_thread(self._plan_with_room, req.plan)
        stored = {"plan": plan.model_dump(mode="json"), "label": req.label, "part_number": req.part_number,
                  "serial_number": req.serial_number}
        try:
            job, created = await self.daemon.manager.submit(name, stored, len(plan.steps), idempotency_key,
                                                            request_hash(req.model_dump(mode="json")))
        except IdempotencyConflict as e:
            raise ApiProblem(409, "Idempotency-Key reused", str(e)) from e
        return await self.read(self._body, job), created

    def _plan_with_room(self, name: str | None) -> tuple[str, Plan]:
        """(thread) The plan ``name`` names (None: the default) and its name, when there is room for its scans."""
        d = self.daemon
        if name is not None and name not in d.plans.names():
            raise ApiProblem(404, "Unknown plan", f"no plan named {name!r}; see /v1/plans")
        try:
            plan = d.plans.get(name)
        except PlanError as e:
            raise ApiProblem(409, "Plan is invalid", str(e)) from e
        need, free = d.bytes_needed(sum(s.kind == "scan" for s in plan.steps)), d.free_bytes()
        if free < need:
            raise ApiProblem(507, "Insufficient storage", f"the job needs {need / 1e6:.0f} MB free for its scans and "
                             f"exports; {free / 1e6:.0f} MB are free in the state folder")
        return name or d.plans.default_name, plan

    async def act(self, job_id: str, verb: str) -> Job:
        """``cancel``, ``pause`` or ``resume`` the job (the manager's rules; 404, 409 as it refuses)."""
        manager = self.daemon.manager
        action = {"cancel": manager.cancel, "pause": manager.pause, "resume": manager.resume}[verb]
        return await self.read(self._body, await action(job_id))

    def job_dir(self, job_id: str) -> Path:
        return self.daemon.store.job_dir(job_id)

    async def job_file(self, job_id: str, name: str) -> Path:
        """The path of one of the job's outputs; 409 while the job may still make it, 404 when it never will."""
        def existing() -> Path:
            job = self.daemon.manager.get(job_id)
            path = self.daemon.store.job_dir(job.id) / name
            if not path.is_file():
                raise ApiProblem(409 if job.state not in FINAL_STATES else 404,
                                 "Result not available", f"job {job_id} is {job.state}; {name} is not there")
            return path

        return await self.read(existing)

    async def read_job_file(self, job_id: str, name: str) -> bytes:
        """The bytes of one of the job's outputs (:meth:`job_file`), read off the loop."""
        return await asyncio.to_thread((await self.job_file(job_id, name)).read_bytes)

    # ------------------------------------------------------------ cell

    def devices(self) -> dict:
        """The supervisor's snapshot (in memory): devices, latch, robots moving."""
        return self.daemon.supervisor.snapshot()

    def safety_inputs(self) -> SafetyState | None:
        """The safety inputs as the control loop last read them (None before the first read)."""
        return self.daemon.supervisor.safety_inputs

    async def safety_stop(self, via: str = "REST") -> dict:
        """Latch an operator safety stop (the reason names the interface ``via``); the devices' snapshot."""
        await self.daemon.supervisor.trip(f"operator stop ({via})")
        return self.devices()

    async def safety_reset(self) -> dict:
        """Clear the latch; 409 while the e-stop or light curtain still forbid motion."""
        try:
            await self.daemon.supervisor.reset_safety()
        except SafetyStop as e:
            raise ApiProblem(409, "Safety stop still active", e.reason) from e
        return self.devices()

    async def calibration(self) -> dict:
        """The installation transforms (4x4 lists, mm) a job started now would use and their source; none, with
        the reason, when they cannot be resolved
        (:func:`~tandemscan.daemon.calibration.current.installation_for_job`)."""
        config = await asyncio.to_thread(resolve_installation, self.daemon.config)
        try:
            installation = await asyncio.to_thread(installation_for_job, config)
        except (InstallationError, OSError, ValueError, KeyError) as e:
            log.warning("installation not resolved: %s", e)
            transforms, error = {}, str(e)
        else:
            transforms = {n: np.asarray(getattr(installation, n), float).tolist() for n in CALIBRATION_TRANSFORMS}
            error = None
        job = config.job
        verification = await asyncio.to_thread(last_verification, config)
        return {"source": job.installation_source, "file": str(job.calibration_file) if job.calibration_file else None,
                "transforms": transforms, "error": error, "verification": verification}

    async def plans(self) -> list[dict]:
        return await asyncio.to_thread(self.daemon.plans.summaries)

    # ------------------------------------------------------------ service

    async def health(self) -> dict:
        return await self.read(self.daemon.health)

    async def metrics(self) -> bytes:
        """Prometheus text: the job counts read in the store thread, the rest from memory on the loop."""
        self.daemon.job_counts = await self.read(self.daemon.store.count_by_state)
        return generate_latest(self.daemon.registry)

    # ------------------------------------------------------------ events

    def subscribe(self) -> Subscription:
        return self.daemon.bus.subscribe()

    @property
    def heartbeat_s(self) -> float:
        return self.daemon.sse_heartbeat_s

    async def missed_events(self, after: int | None, job_id: str | None) -> tuple[int, str]:
        """``(last id seen, the events to replay as one server-sent-events text)``: those after ``after`` (of
        ``job_id``, when given) from the journal, or none when ``after`` is None; read and encoded in the store
        thread, so that a long replay is one write for the loop."""
        store = self.daemon.store
        if after is None:
            return await self.read(store.last_event_seq), ""

        def replay() -> tuple[int, str]:
            events = store.events(after, job_id, MAX_REPLAYED_EVENTS)
            return max((ev.seq for ev in events), default=after), "".join(sse_text(ev) for ev in events)

        return await self.read(replay)


def facade_of(request: Request) -> ServiceFacade:
    """The service facade of the app serving ``request`` (a route dependency)."""
    return request.app.state.facade


Facade = Annotated[ServiceFacade, Depends(facade_of)]
