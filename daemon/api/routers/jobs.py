"""``/v1/jobs``: queue a job, list and read jobs, cancel, pause and resume one (docs/daemon.md)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Header, Query, Request
from fastapi.responses import JSONResponse, Response
from tandemscan.daemon.api.facade import Facade
from tandemscan.daemon.api.guard import require_token
from tandemscan.daemon.api.models import PROBLEM_RESPONSES, Job, JobId, JobPage, JobRequest, JobStateName

router = APIRouter(tags=["jobs"])
MUTATING = [Depends(require_token)]


@router.post("/v1/jobs", status_code=202, response_model=Job, dependencies=MUTATING,
             responses={**PROBLEM_RESPONSES, 200: {"model": Job, "description": "a retry: the job already made"}})
async def submit_job(
    facade: Facade, req: JobRequest,
    idempotency_key: Annotated[str | None, Header(max_length=200)] = None,
) -> Response:
    """Queue a job (202 with its URL in ``Location``). A retry with the same ``Idempotency-Key`` and
    body returns the same job (200); the same key with another body is refused (409); an unknown plan
    is 404."""
    job, created = await facade.submit(req, idempotency_key)
    headers = {"Location": f"/v1/jobs/{job.id}"}
    if not created:
        headers["Idempotent-Replayed"] = "true"
    return JSONResponse(job.model_dump(mode="json"), status_code=202 if created else 200, headers=headers)


@router.get("/v1/jobs", response_model=JobPage, responses=PROBLEM_RESPONSES)
async def list_jobs(
    request: Request, facade: Facade,
    state: Annotated[list[JobStateName] | None, Query(description="repeat to match any of several")] = None,
    plan: Annotated[str | None, Query(max_length=200)] = None,
    limit: Annotated[int, Query(ge=1, le=500)] = 50,
    offset: Annotated[int, Query(ge=0, le=10**9)] = 0,
) -> Response:
    """Jobs newest first, filtered by state and plan, in pages."""
    url = request.url
    page = await facade.jobs_json(state, plan, limit, offset,
                                  lambda nxt: str(url.include_query_params(offset=nxt, limit=limit)))
    return Response(page, media_type="application/json")


@router.get("/v1/jobs/{job_id}", response_model=Job, responses=PROBLEM_RESPONSES)
async def get_job(job_id: JobId, facade: Facade) -> Response:
    """State, progress, the step under way and figures so far."""
    return Response(await facade.job_json(job_id), media_type="application/json")


@router.post("/v1/jobs/{job_id}/cancel", response_model=Job, dependencies=MUTATING, responses=PROBLEM_RESPONSES)
async def cancel_job(job_id: JobId, facade: Facade) -> Job:
    """Cancel a queued, running or paused job (motion stops at once)."""
    return await facade.act(job_id, "cancel")


@router.post("/v1/jobs/{job_id}/pause", response_model=Job, dependencies=MUTATING, responses=PROBLEM_RESPONSES)
async def pause_job(job_id: JobId, facade: Facade) -> Job:
    """Pause a running job at its next step boundary."""
    return await facade.act(job_id, "pause")


@router.post("/v1/jobs/{job_id}/resume", response_model=Job, dependencies=MUTATING, responses=PROBLEM_RESPONSES)
async def resume_job(job_id: JobId, facade: Facade) -> Job:
    """Resume a paused job; after a safety stop this resets the latch, refused while inputs forbid motion."""
    return await facade.act(job_id, "resume")
