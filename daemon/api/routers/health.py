"""The service itself: ``/v1/health`` and Prometheus ``/metrics`` (docs/daemon.md)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST
from tandemscan.daemon.api.facade import Facade
from tandemscan.daemon.api.models import Health

router = APIRouter(tags=["service"])


@router.get("/v1/health", response_model=Health)
async def health(facade: Facade) -> Health:
    """Liveness and a one-line state of the cell."""
    return Health.model_validate(await facade.health())


@router.get("/metrics", response_class=Response, responses={200: {"content": {CONTENT_TYPE_LATEST: {}}}})
async def metrics(facade: Facade) -> Response:
    """Prometheus text exposition."""
    return Response(await facade.metrics(), media_type=CONTENT_TYPE_LATEST)
