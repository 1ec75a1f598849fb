"""The REST API for the MES and operators (FastAPI; OpenAPI at ``/openapi.json``, docs at ``/docs``), and
:func:`serve` that runs the daemon behind it with uvicorn (``tandemscan serve``).

A thin HTTP gateway over the daemon: routers per resource (:mod:`tandemscan.daemon.api.routers`: jobs, a job's
files, the cell, events, health and metrics; the console's own, :mod:`tandemscan.daemon.api.console.router`) call
the async service facade (:mod:`tandemscan.daemon.api.facade`), which keeps every blocking call off the event
loop. Errors are RFC 9457 problem details (:mod:`tandemscan.daemon.api.errors`). Mutating calls need
``Authorization: Bearer <token>`` when the daemon has a token (:mod:`tandemscan.daemon.api.guard`); without one
the daemon only binds to loopback (see :func:`tandemscan.daemon.api.guard.check_bind`). See docs/daemon.md.
"""

from __future__ import annotations

import errno
import socket
from collections.abc import AsyncIterator, Mapping
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI
from tandemscan.config import load_config
from tandemscan.daemon.api.console.router import router as console_router
from tandemscan.daemon.api.errors import install_problem_handlers
from tandemscan.daemon.api.facade import ServiceFacade
from tandemscan.daemon.api.guard import GuardBody, check_bind, resolve_token
from tandemscan.daemon.api.routers import cell, events, files, health, jobs, parts
from tandemscan.daemon.metrics import RequestTimer
from tandemscan.daemon.service import Daemon, StartupError, resolve_state_dir

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


def listening_socket(host: str, port: int) -> socket.socket:
    """A TCP socket bound to ``host:port`` for the REST server; :class:`~tandemscan.daemon.service.StartupError`
    (``retry`` when the address is in use) when it cannot be bound."""
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host.strip("[]"), port, type=socket.SOCK_STREAM,
                                                             flags=socket.AI_PASSIVE)[0]
        sock = socket.socket(family, kind, proto)
    except OSError as e:
        raise StartupError(f"cannot listen on {host}:{port}: {e}") from e
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
    except OSError as e:
        sock.close()
        raise StartupError(f"cannot listen on {host}:{port}: {e.strerror or e}", e.errno == errno.EADDRINUSE) from e
    return sock


def serve(config_path: Path | str | None = None, host: str | None = None, port: int | None = None,
          environ: Mapping[str, str] | None = None) -> None:
    """Run the daemon and its REST API until SIGTERM/SIGINT (``tandemscan serve``);
    :class:`~tandemscan.daemon.service.StartupError` when its port or state directory cannot be used,
    :class:`~tandemscan.daemon.api.guard.BindRefused` beyond loopback without a token."""
    import uvicorn

    config = load_config(config_path)
    token = resolve_token(config, environ)
    host = host or config.daemon.host
    port = config.daemon.port if port is None else port
    check_bind(host, token)
    sock = listening_socket(host, port)  # before any device is touched: a taken port ends the start at once
    try:
        daemon = Daemon(config, resolve_state_dir(environ), token=token)
        app = create_app(daemon, manage_lifecycle=True)
        uvicorn.Server(uvicorn.Config(app, host=host, port=port, log_config=None, access_log=False,
                                      timeout_graceful_shutdown=10)).run(sockets=[sock])
    finally:
        sock.close()
