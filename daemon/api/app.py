"""The REST API for the MES and operators (FastAPI; OpenAPI at ``/openapi.json``, docs at ``/docs``).

A thin HTTP gateway over the daemon: routers per resource (:mod:`tandemscan.daemon.api.routers`: jobs, a job's
files, the cell, events, health and metrics; the console's own, :mod:`tandemscan.daemon.api.console.router`) call
the async service facade (:mod:`tandemscan.daemon.api.facade`), which keeps every blocking call off the event
loop. Errors are RFC 9457 problem details (:mod:`tandemscan.daemon.api.errors`). Mutating calls need
``Authorization: Bearer <token>`` when the daemon has a token (:mod:`tandemscan.daemon.api.guard`); without one
the daemon only binds to loopback (see :func:`tandemscan.daemon.service.check_bind`). See docs/daemon.md.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import TYPE_CHECKING

from fastapi import FastAPI
from tandemscan.daemon.api.console.router import router as console_router
from tandemscan.daemon.api.errors import install_problem_handlers
from tandemscan.daemon.api.facade import ServiceFacade
from tandemscan.daemon.api.guard import GuardBody
from tandemscan.daemon.api.routers import cell, events, files, health, jobs, parts
from tandemscan.daemon.metrics import RequestTimer

if TYPE_CHECKING:
    from tandemscan.daemon.service import Daemon

ROUTERS = (jobs.router, files.router, parts.router, cell.router, health.router, events.router, console_router)


def create_app(daemon: Daemon, manage_lifecycle: bool = False) -> FastAPI:
    """The FastAPI app over ``daemon``; with ``manage_lifecycle`` the app starts and closes it."""
    facade = ServiceFacade(daemon)
    opcua = None
    if manage_lifecycle and daemon.config.opcua.enabled:  # the OPC UA server beside REST (docs/opcua.md)
        from tandemscan.daemon.api.opcua.server import gateway_for

        opcua = gateway_for(facade)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        if manage_lifecycle:
            if opcua is not None:
                await opcua.prepare()  # before the safety loop runs: it builds the address space on the loop
            await daemon.start()
            if opcua is not None:
                await opcua.start()
        try:
            yield
        finally:
            if manage_lifecycle:
                if opcua is not None:
                    await opcua.stop()
                await daemon.close()
            facade.close()

    app = FastAPI(title="tandemscan", version=daemon.version, lifespan=lifespan,
                  description="Two-robot 3D measurement cell: jobs, devices, calibration, events.")
    app.state.facade = facade
    app.state.opcua = opcua
    app.add_middleware(GuardBody, token=daemon.token, max_body_bytes=daemon.config.daemon.max_body_bytes)
    app.add_middleware(RequestTimer, registry=daemon.registry)
    install_problem_handlers(app)
    for router in ROUTERS:
        app.include_router(router)
    return app
