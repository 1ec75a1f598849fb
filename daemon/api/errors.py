"""Errors of the REST API as RFC 9457 problem details (``application/problem+json``).

A handler raises :class:`ApiProblem` (or the job manager a :class:`~tandemscan.daemon.jobs.manager.JobRequestError`,
which carries its status); :func:`install_problem_handlers` answers those, FastAPI's own HTTP and validation errors and
any unhandled exception (500, logged) with a :class:`~tandemscan.daemon.api.models.Problem` body. See
docs/daemon.md.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from http import HTTPStatus

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match
from tandemscan.daemon.api.models import PROBLEM, Problem
from tandemscan.daemon.jobs.manager import JobRequestError

log = logging.getLogger(__name__)


class ApiProblem(Exception):
    """Raised by a handler or the service facade to answer with a problem document."""

    def __init__(self, status: int, title: str, detail: str | None = None, type_: str = "about:blank"):
        super().__init__(detail or title)
        self.status, self.title, self.detail, self.type = status, title, detail, type_


def problem(status: int, title: str, detail: str | None = None, instance: str | None = None,
            type_: str = "about:blank", errors: list | None = None,
            headers: dict[str, str] | None = None) -> JSONResponse:
    """A problem-details response."""
    body = Problem(type=type_, title=title, status=status, detail=detail, instance=instance, errors=errors)
    return JSONResponse(body.model_dump(exclude_none=True), status_code=status, media_type=PROBLEM,
                        headers=headers)


def title_of(status: int) -> str:
    """The reason phrase of an HTTP status ("Error" for one HTTP does not define)."""
    try:
        return HTTPStatus(status).phrase
    except ValueError:
        return "Error"


async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    headers = getattr(exc, "headers", None)
    if exc.status_code == 405:  # Allow: every method of every route on this path, not only the first
        methods = set()
        for route in _leaf_routes(request.app.routes):
            if route.matches(request.scope)[0] != Match.NONE:
                methods |= set(getattr(route, "methods", None) or ())
        headers = {"Allow": ", ".join(sorted(methods))}
    # FastAPI answers a body it cannot decode (not UTF-8) with 400: a malformed body like any other, 422
    status = 422 if exc.status_code == 400 else exc.status_code
    return problem(status, title_of(status), str(exc.detail), request.url.path, headers=headers)


def _leaf_routes(routes) -> Iterator:
    """The routes of an app, those of its included routers in their place."""
    for route in routes:
        inner = getattr(route, "original_router", None)
        yield from (route,) if inner is None else _leaf_routes(inner.routes)


async def _invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
    errors = [{"loc": [str(p) for p in e.get("loc", ())], "msg": e.get("msg", ""), "type": e.get("type", "")}
              for e in exc.errors()]
    return problem(422, "Invalid request", "; ".join(f"{'.'.join(e['loc'])}: {e['msg']}" for e in errors),
                   request.url.path, errors=errors)


async def _api(request: Request, exc: ApiProblem) -> JSONResponse:
    return problem(exc.status, exc.title, exc.detail, request.url.path, exc.type)


async def _job(request: Request, exc: JobRequestError) -> JSONResponse:
    return problem(exc.status, title_of(exc.status), str(exc), request.url.path)


async def _crash(request: Request, exc: Exception) -> JSONResponse:
    log.exception("unhandled error on %s", request.url.path)
    return problem(500, "Internal error", type(exc).__name__, request.url.path)


def install_problem_handlers(app: FastAPI) -> None:
    """Answer every error of ``app`` with a problem document."""
    app.add_exception_handler(StarletteHTTPException, _http)
    app.add_exception_handler(RequestValidationError, _invalid)
    app.add_exception_handler(ApiProblem, _api)
    app.add_exception_handler(JobRequestError, _job)
    app.add_exception_handler(Exception, _crash)
