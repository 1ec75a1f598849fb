"""A job's outputs: ``/v1/jobs/{id}/cloud``, ``/report``, ``/results.qif`` and ``/files/{name}``
(docs/daemon.md). Files are streamed (Starlette reads them in its thread pool); the report is read off the
loop by the facade."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import FileResponse, Response
from tandemscan.daemon.api.errors import ApiProblem
from tandemscan.daemon.api.facade import Facade
from tandemscan.daemon.api.models import JOB_FILES, PROBLEM_RESPONSES, JobId

router = APIRouter(tags=["jobs"])


@router.get("/v1/jobs/{job_id}/cloud", response_class=FileResponse,
            responses={**PROBLEM_RESPONSES, 200: {"content": {"application/octet-stream": {}},
                                                  "description": "binary PLY, mm"}})
async def get_cloud(job_id: JobId, facade: Facade) -> FileResponse:
    """The stitched cloud (binary PLY, mm), streamed."""
    return FileResponse(await facade.job_file(job_id, "cloud.ply"), media_type="application/octet-stream",
                        filename=f"{job_id}.ply")


@router.get("/v1/jobs/{job_id}/report", responses={**PROBLEM_RESPONSES, 200: {"content": {"application/json": {}}}})
async def get_report(job_id: JobId, facade: Facade) -> Response:
    """The job's report (JSON: accuracy figures, per-scan poses, timings)."""
    return Response(await facade.read_job_file(job_id, "report.json"), media_type="application/json")


@router.get("/v1/jobs/{job_id}/results.qif", response_class=FileResponse,
            responses={**PROBLEM_RESPONSES, 200: {"content": {"application/xml": {}},
                                                  "description": "QIF 3.0 Results (docs/inspection.md)"}})
async def get_results_qif(job_id: JobId, facade: Facade) -> FileResponse:
    """The job's characteristics as a QIF 3.0 Results document, streamed (a job inspected with a template)."""
    return FileResponse(await facade.job_file(job_id, "results.qif"), media_type="application/xml",
                        filename=f"{job_id}-results.qif")


@router.get("/v1/jobs/{job_id}/files/{name}", response_class=FileResponse,
            responses={**PROBLEM_RESPONSES, 200: {"description": "the file, streamed"}})
async def get_job_file(job_id: JobId, name: str, facade: Facade) -> FileResponse:
    """One of the job's exports: ``report.html``, ``cloud.e57``, ``poses.csv``, ``cloud_deviation.ply``."""
    media_type = JOB_FILES.get(name)
    if media_type is None:
        raise ApiProblem(404, "No such job file", f"{name!r} is not one of {', '.join(JOB_FILES)}")
    return FileResponse(await facade.job_file(job_id, name), media_type=media_type, filename=f"{job_id}-{name}")
