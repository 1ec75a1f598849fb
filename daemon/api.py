"""The REST API for the MES and operators (FastAPI; OpenAPI at ``/openapi.json``, docs at ``/docs``).

A thin gateway over the :class:`~tandemscan.daemon.service.Daemon`: jobs, devices, calibration, plans,
health, Prometheus metrics and a server-sent event stream. Errors are RFC 9457 problem details
(``application/problem+json``). Mutating calls need ``Authorization: Bearer <token>`` when the daemon has
a token; without one the daemon only binds to loopback (see :func:`tandemscan.daemon.service.check_bind`).
"""

from __future__ import annotations

import asyncio
import hmac
import json
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Annotated, Any, Literal

from fastapi import Depends, FastAPI, Header, Path, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, Response, StreamingResponse
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from pydantic import BaseModel, ConfigDict, Field
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match
from tandemscan.daemon.job_state import FINAL_STATES, JobState
from tandemscan.daemon.jobs import JobError, request_hash
from tandemscan.daemon.metrics import RequestTimer
from tandemscan.daemon.store import IdempotencyConflict, JobRecord
from tandemscan.drivers.errors import SafetyStop
from tandemscan.pipeline.planning.plan import PlanError

if TYPE_CHECKING:
    from tandemscan.daemon.service import Daemon

log = logging.getLogger(__name__)

PROBLEM = "application/problem+json"
JobId = Annotated[str, Path(pattern=r"^[A-Za-z0-9_-]{1,64}$", description="job id")]
JobStateName = JobState
#: ``Last-Event-ID`` / ``after``: an event sequence number (decimal digits, at most 2**62)
MAX_EVENT_ID = 2**62

# ---------------------------------------------------------------- bodies


class JobRequest(BaseModel):
    """A job to queue. ``{}`` runs the cell's default plan."""

    model_config = ConfigDict(extra="forbid")
    plan: str | None = Field(None, min_length=1, max_length=200, description="a name from /v1/plans")
    label: str | None = Field(None, max_length=200, description="free text for the MES (order, serial)")


class Job(BaseModel):
    """A job: state, progress (0-100), the step under way and figures so far (mm, deg)."""

    id: str
    state: JobStateName
    plan: str
    label: str | None = None
    progress: float = Field(ge=0, le=100)
    current_step: int | None
    steps_total: int
    steps_done: int
    figures: dict[str, Any]
    error: str | None
    attempts: int = Field(description="runner starts: 1, plus one per daemon restart while the job was active")
    created: datetime
    started: datetime | None
    finished: datetime | None
    links: dict[str, str]


class JobPage(BaseModel):
    items: list[Job]
    total: int
    limit: int
    offset: int
    next: str | None = Field(None, description="URL of the next page, when there is one")


class Problem(BaseModel):
    """RFC 9457 problem details."""

    type: str = "about:blank"
    title: str
    status: int
    detail: str | None = None
    instance: str | None = None
    errors: list[dict[str, Any]] | None = None


class Device(BaseModel):
    name: str
    connected: bool
    state: str
    detail: dict[str, Any]
    last_error: str | None
    reconnects: int


class Safety(BaseModel):
    latched: bool
    reason: str | None


class Devices(BaseModel):
    devices: list[Device]
    safety: Safety
    moving: list[str] = Field(description="robots moving now (never more than one)")
    all_connected: bool


class PlanSummary(BaseModel):
    name: str
    valid: bool
    default: bool = False
    part: str | None = None
    steps: int | None = None
    scans: int | None = None
    transfers: int | None = None
    error: str | None = None


class Calibration(BaseModel):
    """The installation transforms the stitch uses (4x4, mm) and where they come from."""

    source: Literal["truth", "nominal", "calibration"]
    file: str | None
    transforms: dict[str, list[list[float]]]
    error: str | None = Field(None, description="why the installation could not be resolved (no transforms then)")


class Health(BaseModel):
    """``degraded`` while a device is down, the safety stop latched, free space under the reserve or a job's
    state held in memory because the journal refuses writes."""

    status: Literal["ok", "degraded"]
    devices_connected: bool = Field(description="every device connected and none reporting a fault")
    devices_down: list[str] = Field(description="devices not connected or reporting a fault")
    safety_latched: bool
    active_job: str | None
    queued_jobs: int
    free_bytes: int = Field(description="free space of the state folder's file system (bytes)")
    storage_low: bool = Field(description="free space under [daemon] reserve_free_bytes")
    storage_error: str | None = Field(description="why a job's state is held in memory (the journal refuses writes)")
    version: str


PROBLEM_RESPONSES: dict[int | str, dict[str, Any]] = {
    code: {"model": Problem, "content": {PROBLEM: {}}} for code in (400, 401, 404, 409, 413, 422, 507)
}

# Exports a finished job serves besides cloud.ply and report.json, with their media types.
JOB_FILES = {
    "report.html": "text/html",
    "cloud.e57": "application/octet-stream",
    "poses.csv": "text/csv",
    "cloud_deviation.ply": "application/octet-stream",
}

# ---------------------------------------------------------------- helpers


def _ts(t: float | None) -> datetime | None:
    return None if t is None else datetime.fromtimestamp(t, UTC)


def job_body(job: JobRecord, steps_done: int) -> Job:
    base = f"/v1/jobs/{job.id}"
    links = {"self": base, "events": f"/v1/events?job={job.id}"}
    if job.state == "succeeded":
        links.update(cloud=f"{base}/cloud", report=f"{base}/report", report_html=f"{base}/files/report.html")
    return Job(id=job.id, state=job.state, plan=job.plan_name, label=job.plan.get("label"),
               progress=job.progress, current_step=job.current_step, steps_total=job.n_steps,
               steps_done=steps_done, figures=job.figures, error=job.error, attempts=job.attempts,
               created=_ts(job.created_s), started=_ts(job.started_s), finished=_ts(job.finished_s), links=links)


def problem(status: int, title: str, detail: str | None = None, instance: str | None = None,
            type_: str = "about:blank", errors: list | None = None,
            headers: dict[str, str] | None = None) -> JSONResponse:
    body = Problem(type=type_, title=title, status=status, detail=detail, instance=instance, errors=errors)
    return JSONResponse(body.model_dump(exclude_none=True), status_code=status, media_type=PROBLEM,
                        headers=headers)


class ApiProblem(Exception):
    """Raised by a handler to answer with a problem document."""

    def __init__(self, status: int, title: str, detail: str | None = None, type_: str = "about:blank"):
        super().__init__(detail or title)
        self.status, self.title, self.detail, self.type = status, title, detail, type_


# ---------------------------------------------------------------- the app


def create_app(daemon: Daemon, manage_lifecycle: bool = False) -> FastAPI:
    """The FastAPI app over ``daemon``; with ``manage_lifecycle`` the app starts and closes it."""

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        if manage_lifecycle:
            await daemon.start()
        try:
            yield
        finally:
            if manage_lifecycle:
                await daemon.close()

    app = FastAPI(title="tandemscan", version=daemon.version, lifespan=lifespan,
                  description="Two-robot 3D measurement cell: jobs, devices, calibration, events.")
    app.add_middleware(GuardBody, token=daemon.token, max_body_bytes=daemon.config.daemon.max_body_bytes)
    app.add_middleware(RequestTimer, registry=daemon.registry)

    # -------------------------------------------------------- errors as problem details

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        headers = getattr(exc, "headers", None)
        if exc.status_code == 405:  # Allow: every method of every route on this path, not only the first
            methods = set()
            for route in app.routes:
                if route.matches(request.scope)[0] != Match.NONE:
                    methods |= set(getattr(route, "methods", None) or ())
            headers = {"Allow": ", ".join(sorted(methods))}
        # FastAPI answers a body it cannot decode (not UTF-8) with 400: a malformed body like any other, 422
        status = 422 if exc.status_code == 400 else exc.status_code
        return problem(status, _title(status), str(exc.detail), request.url.path, headers=headers)

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = [{"loc": [str(p) for p in e.get("loc", ())], "msg": e.get("msg", ""), "type": e.get("type", "")}
                  for e in exc.errors()]
        return problem(422, "Invalid request", "; ".join(f"{'.'.join(e['loc'])}: {e['msg']}" for e in errors),
                       request.url.path, errors=errors)

    @app.exception_handler(ApiProblem)
    async def _api(request: Request, exc: ApiProblem) -> JSONResponse:
        return problem(exc.status, exc.title, exc.detail, request.url.path, exc.type)

    @app.exception_handler(JobError)
    async def _job(request: Request, exc: JobError) -> JSONResponse:
        return problem(exc.status, _title(exc.status), str(exc), request.url.path)

    @app.exception_handler(Exception)
    async def _crash(request: Request, exc: Exception) -> JSONResponse:
        log.exception("unhandled error on %s", request.url.path)
        return problem(500, "Internal error", type(exc).__name__, request.url.path)

    # -------------------------------------------------------- auth

    def require_token(authorization: Annotated[str | None, Header()] = None) -> None:
        token = daemon.token
        if token is None:
            return
        if not _bearer_ok(authorization, token):
            raise StarletteHTTPException(401, "a valid bearer token is required for this call",
                                         headers={"WWW-Authenticate": 'Bearer realm="tandemscan"'})

    Mutating = [Depends(require_token)]
    mgr = daemon.manager

    async def body_of(job: JobRecord) -> Job:
        """The job's resource; its step count read off the event loop."""
        return job_body(job, await asyncio.to_thread(daemon.store.steps_done, job.id))

    # -------------------------------------------------------- jobs

    @app.post("/v1/jobs", status_code=202, response_model=Job, dependencies=Mutating,
              responses={**PROBLEM_RESPONSES, 200: {"model": Job, "description": "a retry: the job already made"}},
              tags=["jobs"])
    async def submit_job(
        request: Request, req: JobRequest,
        idempotency_key: Annotated[str | None, Header(max_length=200)] = None,
    ) -> Response:
        """Queue a job (202 with its URL in ``Location``). A retry with the same ``Idempotency-Key`` and
        body returns the same job (200); the same key with another body is refused (409); an unknown plan
        is 404."""
        if req.plan is not None and req.plan not in daemon.plans.names():
            raise ApiProblem(404, "Unknown plan", f"no plan named {req.plan!r}; see /v1/plans")
        try:
            plan = daemon.plans.get(req.plan)
        except PlanError as e:
            raise ApiProblem(409, "Plan is invalid", str(e)) from e
        need, free = daemon.bytes_needed(sum(s.kind == "scan" for s in plan.steps)), daemon.free_bytes()
        if free < need:
            raise ApiProblem(507, "Insufficient storage", f"the job needs {need / 1e6:.0f} MB free for its scans and "
                             f"exports; {free / 1e6:.0f} MB are free in the state folder")
        stored = {"plan": plan.model_dump(mode="json"), "label": req.label}
        try:
            job, created = await mgr.submit(req.plan or daemon.plans.default_name, stored, len(plan.steps),
                                            idempotency_key, request_hash(req.model_dump(mode="json")))
        except IdempotencyConflict as e:
            raise ApiProblem(409, "Idempotency-Key reused", str(e)) from e
        headers = {"Location": f"/v1/jobs/{job.id}"}
        if not created:
            headers["Idempotent-Replayed"] = "true"
        return JSONResponse((await body_of(job)).model_dump(mode="json"), status_code=202 if created else 200,
                            headers=headers)

    @app.get("/v1/jobs", response_model=JobPage, responses=PROBLEM_RESPONSES, tags=["jobs"])
    async def list_jobs(
        request: Request,
        state: Annotated[list[JobStateName] | None, Query(description="repeat to match any of several")] = None,
        plan: Annotated[str | None, Query(max_length=200)] = None,
        limit: Annotated[int, Query(ge=1, le=500)] = 50,
        offset: Annotated[int, Query(ge=0, le=10**9)] = 0,
    ) -> JobPage:
        """Jobs newest first, filtered by state and plan, in pages."""
        jobs, total = await asyncio.to_thread(daemon.store.list_jobs, state, plan, None, limit, offset)
        nxt = None
        if offset + len(jobs) < total:
            nxt = str(request.url.include_query_params(offset=offset + len(jobs), limit=limit))
        return JobPage(items=[await body_of(mgr.current(j)) for j in jobs], total=total, limit=limit, offset=offset,
                       next=nxt)

    @app.get("/v1/jobs/{job_id}", response_model=Job, responses=PROBLEM_RESPONSES, tags=["jobs"])
    async def get_job(job_id: JobId) -> Job:
        """State, progress, the step under way and figures so far."""
        return await body_of(await asyncio.to_thread(mgr.get, job_id))

    @app.post("/v1/jobs/{job_id}/cancel", response_model=Job, dependencies=Mutating,
              responses=PROBLEM_RESPONSES, tags=["jobs"])
    async def cancel_job(job_id: JobId) -> Job:
        """Cancel a queued, running or paused job (motion stops at once)."""
        return await body_of(await mgr.cancel(job_id))

    @app.post("/v1/jobs/{job_id}/pause", response_model=Job, dependencies=Mutating,
              responses=PROBLEM_RESPONSES, tags=["jobs"])
    async def pause_job(job_id: JobId) -> Job:
        """Pause a running job at its next step boundary."""
        return await body_of(await mgr.pause(job_id))

    @app.post("/v1/jobs/{job_id}/resume", response_model=Job, dependencies=Mutating,
              responses=PROBLEM_RESPONSES, tags=["jobs"])
    async def resume_job(job_id: JobId) -> Job:
        """Resume a paused job; after a safety stop this resets the latch, refused while inputs forbid motion."""
        return await body_of(await mgr.resume(job_id))

    def artifact(job_id: str, name: str):
        job = mgr.get(job_id)
        path = daemon.store.job_dir(job.id) / name
        if not path.is_file():
            raise ApiProblem(409 if job.state not in FINAL_STATES else 404,
                             "Result not available", f"job {job_id} is {job.state}; {name} is not there")
        return path

    @app.get("/v1/jobs/{job_id}/cloud", response_class=FileResponse, tags=["jobs"],
             responses={**PROBLEM_RESPONSES, 200: {"content": {"application/octet-stream": {}},
                                                   "description": "binary PLY, mm"}})
    async def get_cloud(job_id: JobId) -> FileResponse:
        """The stitched cloud (binary PLY, mm), streamed."""
        return FileResponse(artifact(job_id, "cloud.ply"), media_type="application/octet-stream",
                            filename=f"{job_id}.ply")

    @app.get("/v1/jobs/{job_id}/report", tags=["jobs"],
             responses={**PROBLEM_RESPONSES, 200: {"content": {"application/json": {}}}})
    async def get_report(job_id: JobId) -> Response:
        """The job's report (JSON: accuracy figures, per-scan poses, timings)."""
        return Response(artifact(job_id, "report.json").read_bytes(), media_type="application/json")

    @app.get("/v1/jobs/{job_id}/files/{name}", response_class=FileResponse, tags=["jobs"],
             responses={**PROBLEM_RESPONSES, 200: {"description": "the file, streamed"}})
    async def get_job_file(job_id: JobId, name: str) -> FileResponse:
        """One of the job's exports: ``report.html``, ``cloud.e57``, ``poses.csv``, ``cloud_deviation.ply``."""
        media_type = JOB_FILES.get(name)
        if media_type is None:
            raise ApiProblem(404, "No such job file", f"{name!r} is not one of {', '.join(JOB_FILES)}")
        return FileResponse(artifact(job_id, name), media_type=media_type, filename=f"{job_id}-{name}")

    # -------------------------------------------------------- cell

    @app.get("/v1/devices", response_model=Devices, tags=["cell"])
    async def devices() -> Devices:
        """Every device's connection and state, the safety latch and which robot moves."""
        return Devices.model_validate(daemon.supervisor.snapshot())

    @app.post("/v1/safety/stop", response_model=Devices, dependencies=Mutating, responses=PROBLEM_RESPONSES,
              tags=["cell"])
    async def safety_stop() -> Devices:
        """Latch an operator safety stop: all motion halts, the running job goes to paused_safety."""
        await daemon.supervisor.trip("operator stop (REST)")
        return Devices.model_validate(daemon.supervisor.snapshot())

    @app.post("/v1/safety/reset", response_model=Devices, dependencies=Mutating, responses=PROBLEM_RESPONSES,
              tags=["cell"])
    async def safety_reset() -> Devices:
        """Clear the safety latch; refused (409) while the e-stop or light curtain still forbid motion."""
        try:
            await daemon.supervisor.reset_safety()
        except SafetyStop as e:
            raise ApiProblem(409, "Safety stop still active", e.reason) from e
        return Devices.model_validate(daemon.supervisor.snapshot())

    @app.get("/v1/calibration", response_model=Calibration, tags=["cell"])
    async def calibration() -> Calibration:
        """The installation transforms in use (4x4, mm) and their source."""
        return Calibration.model_validate(daemon.calibration())

    @app.get("/v1/plans", response_model=list[PlanSummary], tags=["cell"])
    async def plans() -> list[PlanSummary]:
        """Plans a job can name (``{}`` uses the default)."""
        summaries = await asyncio.to_thread(daemon.plans.summaries)
        return [PlanSummary.model_validate(s) for s in summaries]

    @app.get("/v1/health", response_model=Health, tags=["service"])
    async def health() -> Health:
        """Liveness and a one-line state of the cell."""
        return Health.model_validate(await asyncio.to_thread(daemon.health))

    @app.get("/metrics", tags=["service"], response_class=Response,
             responses={200: {"content": {CONTENT_TYPE_LATEST: {}}}})
    async def metrics() -> Response:
        """Prometheus text exposition."""
        return Response(generate_latest(daemon.registry), media_type=CONTENT_TYPE_LATEST)

    @app.get("/v1/events", tags=["service"], response_class=StreamingResponse,
             responses={**PROBLEM_RESPONSES, 200: {"content": {"text/event-stream": {}}}})
    async def events(
        request: Request,
        job: Annotated[str | None, Query(max_length=64, description="only this job's events")] = None,
        after: Annotated[int | None, Query(ge=0, le=2**62, description="replay events after this id")] = None,
        last_event_id: Annotated[str | None, Header()] = None,
    ) -> StreamingResponse:
        """Server-sent events (``state``, ``progress``, ``device``, ``safety``); reconnect with
        ``Last-Event-ID`` (or ``after``) to replay what was missed from the journal. A ``Last-Event-ID`` that
        is not an event id (decimal digits, at most 2**62) is a 400 problem."""
        start = after
        if start is None and last_event_id is not None:
            start = parse_event_id(last_event_id)
        return StreamingResponse(_event_stream(daemon, request, job, start), media_type="text/event-stream",
                                 headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"})

    from tandemscan.daemon.console.router import console_router  # it imports this module's bodies

    app.include_router(console_router(daemon, require_token))
    return app


def parse_event_id(value: str) -> int:
    """An SSE ``Last-Event-ID`` as an event sequence number; :class:`ApiProblem` 400 when it is not one."""
    text = value.strip()
    if not (text.isascii() and text.isdigit() and len(text) <= 19 and int(text) <= MAX_EVENT_ID):
        raise ApiProblem(400, "Malformed Last-Event-ID", f"Last-Event-ID must be an event id (decimal digits up to "
                         f"{MAX_EVENT_ID}); got {value[:40]!r}")
    return int(text)


class GuardBody:
    """ASGI middleware in front of every handler: a mutating request without the bearer token is refused (401)
    before its body is read, and a body over ``max_body_bytes`` (declared or streamed) is refused with 413."""

    def __init__(self, app, token: str | None, max_body_bytes: int):
        self.app, self.token, self.max_body_bytes = app, token, max_body_bytes

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", ())}
        if self.token is not None and scope["method"] not in ("GET", "HEAD", "OPTIONS") \
                and not _bearer_ok(headers.get("authorization"), self.token):
            return await problem(401, "Unauthorized", "a valid bearer token is required for this call", scope["path"],
                                 headers={"WWW-Authenticate": 'Bearer realm="tandemscan"'})(scope, receive, send)
        declared = headers.get("content-length", "")
        if declared.isdigit() and int(declared) > self.max_body_bytes:
            return await self._too_large(scope, receive, send)
        seen, refused = 0, False

        async def counted():
            nonlocal seen, refused
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.max_body_bytes and not refused:
                    refused = True
                    await self._too_large(scope, receive, send)
                    return {"type": "http.disconnect"}  # the handler stops reading; its answer is dropped
            return message

        async def unless_refused(message) -> None:
            if not refused:
                await send(message)

        await self.app(scope, counted, unless_refused)

    async def _too_large(self, scope, receive, send) -> None:
        await problem(413, "Content Too Large", f"request bodies are limited to {self.max_body_bytes} bytes",
                      scope["path"], headers={"Connection": "close"})(scope, receive, send)


def _bearer_ok(authorization: str | None, token: str) -> bool:
    """Whether an ``Authorization`` header carries ``token`` as its bearer token (constant-time compare)."""
    scheme, _, given = (authorization or "").partition(" ")
    return scheme.lower() == "bearer" and hmac.compare_digest(given.strip().encode(), token.encode())


async def _event_stream(daemon: Daemon, request: Request, job: str | None, after: int | None) -> AsyncIterator[str]:
    with daemon.bus.subscribe() as sub:
        # live events up to here are old
        seen = await asyncio.to_thread(daemon.store.last_event_seq) if after is None else after
        missed = [] if after is None else await asyncio.to_thread(daemon.store.events, after, job, 10000)
        for ev in missed:
            seen = max(seen, ev.seq)
            yield _sse(ev)
        yield ": connected\n\n"
        while True:
            try:
                ev = await asyncio.wait_for(sub.get(), daemon.sse_heartbeat_s)
            except TimeoutError:
                if await request.is_disconnected():
                    return
                yield ": ping\n\n"
                continue
            if ev.seq <= seen or (job is not None and ev.job_id != job):
                continue
            yield _sse(ev)


def _sse(ev) -> str:
    data = {"job_id": ev.job_id, **ev.data, "t_s": ev.t_s}
    return f"id: {ev.seq}\nevent: {ev.kind}\ndata: {json.dumps(data)}\n\n"


def _title(status: int) -> str:
    from http import HTTPStatus

    try:
        return HTTPStatus(status).phrase
    except ValueError:
        return "Error"
