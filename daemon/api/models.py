"""The REST API's bodies (pydantic): what each route takes and answers, as ``/openapi.json`` publishes them.

Times are ISO 8601 UTC on the wire; figures in mm and degrees as the job's report gives them; installation
transforms as 4x4 nested lists (mm). Errors are RFC 9457 problem details (:class:`Problem`). See docs/daemon.md.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Annotated, Any, Literal

from fastapi import Path
from pydantic import BaseModel, ConfigDict, Field
from tandemscan.daemon.job_state import COMPLETED_STATES, JobState
from tandemscan.daemon.store.job_store import JobRecord

PROBLEM = "application/problem+json"
JobId = Annotated[str, Path(pattern=r"^[A-Za-z0-9_-]{1,64}$", description="job id")]
JobStateName = JobState
#: ``Last-Event-ID`` / ``after``: an event sequence number (decimal digits, at most 2**62)
MAX_EVENT_ID = 2**62


class JobRequest(BaseModel):
    """A job to queue. ``{}`` runs the cell's default plan."""

    model_config = ConfigDict(extra="forbid")
    plan: str | None = Field(None, min_length=1, max_length=200, description="a name from /v1/plans")
    label: str | None = Field(None, max_length=200, description="free text for the MES (order, serial)")
    part_number: str | None = Field(None, max_length=200, description="the part number (OPC UA ProductId)")
    serial_number: str | None = Field(None, max_length=200, description="the part's serial number (OPC UA PartId)")


class Job(BaseModel):
    """A job: state, progress (0-100), the step under way and figures so far (mm, deg)."""

    id: str
    state: JobStateName
    plan: str
    label: str | None = None
    part_number: str | None = None
    serial_number: str | None = None
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

    source: Literal["nominal", "calibration"]
    file: str | None
    transforms: dict[str, list[list[float]]]
    error: str | None = Field(None, description="why the installation could not be resolved (no transforms then)")
    verification: dict | None = Field(None, description="the last interim verification (`tandemscan verify`): "
                                      "result, errors against their MPEs, created_utc, age_h, summary; none on record")


class Health(BaseModel):
    """``degraded`` while a device is down, the safety stop latched, free space under the reserve, or a job's
    state or device events held in memory because the journal refuses writes, or the active job measuring again a
    scan whose file was damaged."""

    status: Literal["ok", "degraded"]
    devices_connected: bool = Field(description="every device connected and none reporting a fault")
    devices_down: list[str] = Field(description="devices not connected or reporting a fault")
    safety_latched: bool
    active_job: str | None
    queued_jobs: int
    free_bytes: int = Field(description="free space of the state folder's file system (bytes)")
    storage_low: bool = Field(description="free space under [daemon] reserve_free_bytes")
    storage_error: str | None = Field(description="why a job's state is held in memory (the journal refuses writes)")
    events_not_journaled: int = Field(0, description="device and safety events published but not journaled yet "
                                      "(the journal refuses writes; retried)")
    event_journal_failures: int = Field(0, description="journal writes of device events refused since the start")
    damaged_scans: list[dict[str, Any]] = Field(
        default_factory=list, description="committed scans found missing or altered when their job resumed (job, "
        "step, scan_index, file, reason), since the start; degraded while their job is active (measured again)")
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
    "ground_truth.json": "application/json",  # the simulated cell's scores of the job (job_report.GROUND_TRUTH_FILE)
}


def _ts(t: float | None) -> datetime | None:
    return None if t is None else datetime.fromtimestamp(t, UTC)


def job_body(job: JobRecord, steps_done: int) -> Job:
    """The wire form of a job read from the store (``steps_done``: its committed steps)."""
    base = f"/v1/jobs/{job.id}"
    links = {"self": base, "events": f"/v1/events?job={job.id}"}
    if job.state in COMPLETED_STATES:
        links.update(cloud=f"{base}/cloud", report=f"{base}/report", report_html=f"{base}/files/report.html",
                     results_qif=f"{base}/results.qif")
    return Job(id=job.id, state=job.state, plan=job.plan_name, label=job.plan.get("label"),
               part_number=job.plan.get("part_number"), serial_number=job.plan.get("serial_number"),
               progress=job.progress, current_step=job.current_step, steps_total=job.n_steps,
               steps_done=steps_done, figures=job.figures, error=job.error, attempts=job.attempts,
               created=_ts(job.created_s), started=_ts(job.started_s), finished=_ts(job.finished_s), links=links)


class TrendPoint(BaseModel):
    """One serial's result of a characteristic (mm; ``actual_mm`` null where it was not measured)."""

    serial: str | None
    job: str
    measured: datetime
    actual_mm: float | None
    status: str


class CharacteristicTrend(BaseModel):
    """A characteristic's last results over serials and their individuals chart (mm): mean, standard
    deviation, control limits (mean +/- 3 moving range / 1.128), Cp/Cpk (within) and Pp/Ppk (overall), and
    why it drifts ("" when it does not; docs/quality.md, "Serials and trends")."""

    part_number: str
    characteristic: str
    name: str
    lower_mm: float
    upper_mm: float
    points: list[TrendPoint]
    mean_mm: float | None
    std_mm: float | None
    sigma_within_mm: float | None
    ucl_mm: float | None
    lcl_mm: float | None
    cp: float | None
    cpk: float | None
    pp: float | None
    ppk: float | None
    drift: str


def trend_body(trend) -> CharacteristicTrend:
    """The wire form of a :class:`~tandemscan.daemon.store.part_results.Trend`."""
    c = trend.chart
    chart = {k: getattr(c, k) if c is not None else None
             for k in ("mean_mm", "std_mm", "sigma_within_mm", "ucl_mm", "lcl_mm", "cp", "cpk", "pp", "ppk")}
    return CharacteristicTrend(
        part_number=trend.part_number, characteristic=trend.characteristic, name=trend.name,
        lower_mm=trend.lower_mm, upper_mm=trend.upper_mm,
        points=[TrendPoint(serial=m.serial, job=m.job_id, measured=_ts(m.measured_s), actual_mm=m.actual_mm,
                           status=m.status) for m in trend.series],
        drift=c.drift if c is not None else "", **chart)
