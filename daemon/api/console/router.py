"""The operator console's routes (docs/console.md): the page and its assets (public), and the data only the
console needs (bearer token, like the rest of the API when the daemon has one):

- ``GET /`` and ``GET /console/{name}``: the page, its script and style sheet, from the package;
- ``GET /v1/session``: 200 when the caller's token is accepted (the console's sign-in check);
- ``GET /v1/safety``: the latch and the safety inputs now, and whether a reset would be accepted;
- ``GET /v1/jobs/{id}/plan``: a job's plan as a top view: the AGVs' stations per step (floor frame F, mm);
- ``GET /v1/jobs/{id}/view``: the thinned binary cloud of a finished job (:mod:`.cloud_view`).
"""

from __future__ import annotations

import asyncio
import logging
from importlib import resources
from typing import Literal

from fastapi import APIRouter, Depends, Path
from fastapi.responses import FileResponse, HTMLResponse, Response
from pydantic import BaseModel, Field
from tandemscan.daemon.api.console.cloud_view import MEDIA_TYPE, CloudViewError, view_file
from tandemscan.daemon.api.errors import ApiProblem
from tandemscan.daemon.api.facade import Facade
from tandemscan.daemon.api.guard import require_token
from tandemscan.daemon.api.models import PROBLEM_RESPONSES, JobId
from tandemscan.daemon.job_state import FINAL_STATES
from tandemscan.drivers.errors import DeviceError
from tandemscan.pipeline.planning.plan import MoveMeasure, MoveTracker, Plan

log = logging.getLogger(__name__)

# The console's files in the package (tandemscan/daemon/api/console/static), with their media types.
ASSETS = {
    "console.js": "text/javascript",
    "view3d.js": "text/javascript",
    "plan.js": "text/javascript",
    "console.css": "text/css",
}
router = APIRouter(tags=["console"])
AUTHORISED = [Depends(require_token)]


class Session(BaseModel):
    """The caller may use the API: ``token_required`` says whether the daemon asks for a bearer token."""

    token_required: bool
    version: str


class SafetyNow(BaseModel):
    """The safety latch and inputs now; ``reset_allowed``: a reset (or a resume) would clear the latch."""

    latched: bool
    reason: str | None
    inputs_readable: bool
    estop: bool | None = Field(description="e-stop pressed (None: the inputs could not be read)")
    light_curtain_broken: bool | None
    reset_allowed: bool


class Station(BaseModel):
    """Where a plan moves one AGV: floor frame F, mm and rad (heading about z), and the scans taken there."""

    step: int = Field(description="index of the move step in the plan")
    robot: Literal["measure", "tracking"]
    x_mm: float
    y_mm: float
    heading_rad: float
    scan_steps: list[int] = Field(description="scan steps taken while the AGV stands here")


class PlanView(BaseModel):
    """A job's plan as a top view: the stations of both AGVs in step order, and which devices report each
    AGV's odometry pose (``detail.x_mm``, ``y_mm``, ``heading_rad`` of ``GET /v1/devices``)."""

    plan: str
    steps_total: int
    step_labels: list[str] = Field(description="what each step does, e.g. 'scan: station 0 x -1010 z 650'")
    stations: list[Station]
    chassis_devices: dict[str, str] = Field(description="robot (measure, tracking) -> device name")


def plan_view(plan: Plan, chassis_devices: dict[str, str]) -> PlanView:
    """The stations of ``plan``: each AGV move, with the scan steps until that AGV moves again."""
    stations: list[Station] = []
    current = {}
    for i, step in enumerate(plan.steps):
        if isinstance(step, MoveMeasure | MoveTracker):
            robot = "measure" if isinstance(step, MoveMeasure) else "tracking"
            current[robot] = Station(step=i, robot=robot, x_mm=step.x_mm, y_mm=step.y_mm,
                                     heading_rad=step.heading_rad, scan_steps=[])
            stations.append(current[robot])
        elif step.kind == "scan" and "measure" in current:
            current["measure"].scan_steps.append(i)
    labels = [f"{s.kind.replace('_', ' ')}: {s.label}" if getattr(s, "label", "") else s.kind.replace("_", " ")
              for s in plan.steps]
    return PlanView(plan=plan.name, steps_total=len(plan.steps), step_labels=labels, stations=stations,
                    chassis_devices=chassis_devices)


def _asset_text(name: str) -> str:
    return resources.files("tandemscan.daemon.api.console").joinpath("static", name).read_text(encoding="utf-8")


@router.get("/", response_class=HTMLResponse, responses={200: {"content": {"text/html": {}}}})
async def console_page() -> HTMLResponse:
    """The operator console (one page; it signs in with the API token and keeps it for the tab)."""
    return HTMLResponse(await asyncio.to_thread(_asset_text, "index.html"), headers={"Cache-Control": "no-cache"})


@router.get("/console/{name}", response_class=Response, responses={
    **PROBLEM_RESPONSES, 200: {"content": {t: {} for t in set(ASSETS.values())}}})
async def console_asset(name: str = Path(max_length=64)) -> Response:
    """One of the console's script and style files (404 for any other name)."""
    if name not in ASSETS:
        raise ApiProblem(404, "No such console file", f"{name!r} is not one of {', '.join(ASSETS)}")
    return Response(await asyncio.to_thread(_asset_text, name), media_type=ASSETS[name],
                    headers={"Cache-Control": "no-cache"})


@router.get("/v1/session", response_model=Session, dependencies=AUTHORISED, responses=PROBLEM_RESPONSES)
async def session(facade: Facade) -> Session:
    """200 when the caller's bearer token is accepted (or the daemon needs none); 401 otherwise."""
    return Session(token_required=facade.token is not None, version=facade.version)


@router.get("/v1/safety", response_model=SafetyNow, dependencies=AUTHORISED, responses=PROBLEM_RESPONSES)
async def safety_now(facade: Facade) -> SafetyNow:
    """The safety latch, the e-stop and light curtain as read now, and whether a reset would be accepted."""
    sup = facade.daemon.supervisor
    state = None
    if sup.safety_io is not None:
        try:
            state = await asyncio.wait_for(sup.safety_io.read(), sup.device_timeout_s)
        except (DeviceError, TimeoutError, OSError) as e:
            log.warning("safety inputs unreadable: %s", e)
    readable = sup.safety_io is None or state is not None
    return SafetyNow(latched=sup.latched_reason is not None, reason=sup.latched_reason,
                     inputs_readable=readable, estop=None if state is None else state.estop,
                     light_curtain_broken=None if state is None else state.light_curtain_broken,
                     reset_allowed=readable and (state is None or state.motion_allowed))


@router.get("/v1/jobs/{job_id}/plan", response_model=PlanView, dependencies=AUTHORISED, responses=PROBLEM_RESPONSES)
async def job_plan(job_id: JobId, facade: Facade) -> PlanView:
    """The job's plan as a top view: each AGV station (floor frame F, mm, rad) and its scan steps."""
    job = await facade.job_record(job_id)
    plan = await asyncio.to_thread(Plan.model_validate, job.plan["plan"])
    cell = facade.daemon.cell
    return plan_view(plan, {"measure": cell.measure_chassis.name, "tracking": cell.tracking_chassis.name})


@router.get("/v1/jobs/{job_id}/view", response_class=FileResponse, dependencies=AUTHORISED, responses={
    **PROBLEM_RESPONSES, 200: {"content": {MEDIA_TYPE: {}},
                               "description": "thinned cloud (about 200 k points), binary, mm"}})
async def job_cloud_view(job_id: JobId, facade: Facade) -> FileResponse:
    """A finished job's stitched cloud thinned to about 200 k points with its deviations from CAD, in the
    compact binary form of docs/console.md (float32 mm, the report's colour scale and tolerance band)."""
    job = await facade.job_record(job_id)
    job_dir = facade.job_dir(job.id)
    if job.state not in FINAL_STATES or not await asyncio.to_thread((job_dir / "report.json").is_file):
        raise ApiProblem(409 if job.state not in FINAL_STATES else 404, "Result not available",
                         f"job {job_id} is {job.state}; it has no stitched cloud")
    try:
        path = await asyncio.to_thread(view_file, job_dir)
    except CloudViewError as e:
        raise ApiProblem(404, "Result not available", str(e)) from e
    return FileResponse(path, media_type=MEDIA_TYPE, filename=f"{job_id}-view.bin")
