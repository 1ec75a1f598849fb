"""The cell: ``/v1/devices``, ``/v1/safety/stop`` and ``/reset``, ``/v1/calibration`` and ``/v1/plans``
(docs/daemon.md)."""

from __future__ import annotations

from fastapi import APIRouter, Depends
from tandemscan.daemon.api.facade import Facade
from tandemscan.daemon.api.guard import require_token
from tandemscan.daemon.api.models import PROBLEM_RESPONSES, Calibration, Devices, PlanSummary

router = APIRouter(tags=["cell"])
MUTATING = [Depends(require_token)]


@router.get("/v1/devices", response_model=Devices)
async def devices(facade: Facade) -> Devices:
    """Every device's connection and state, the safety latch and which robot moves."""
    return Devices.model_validate(facade.devices())


@router.post("/v1/safety/stop", response_model=Devices, dependencies=MUTATING, responses=PROBLEM_RESPONSES)
async def safety_stop(facade: Facade) -> Devices:
    """Latch an operator safety stop: all motion halts, the running job goes to paused_safety."""
    return Devices.model_validate(await facade.safety_stop())


@router.post("/v1/safety/reset", response_model=Devices, dependencies=MUTATING, responses=PROBLEM_RESPONSES)
async def safety_reset(facade: Facade) -> Devices:
    """Clear the safety latch; refused (409) while the e-stop or light curtain still forbid motion."""
    return Devices.model_validate(await facade.safety_reset())


@router.get("/v1/calibration", response_model=Calibration)
async def calibration(facade: Facade) -> Calibration:
    """The installation transforms in use (4x4, mm) and their source."""
    return Calibration.model_validate(await facade.calibration())


@router.get("/v1/plans", response_model=list[PlanSummary])
async def plans(facade: Facade) -> list[PlanSummary]:
    """Plans a job can name (``{}`` uses the default)."""
    return [PlanSummary.model_validate(s) for s in await facade.plans()]
