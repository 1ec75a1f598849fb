"""Who may call what: the bearer token of mutating calls, where the daemon may listen without one, and the
request-body limit.

Environment: ``TANDEMSCAN_API_TOKEN`` (bearer token of mutating calls; overrides ``[daemon] api_token``).
:func:`check_bind` refuses to listen beyond loopback without a token (the REST API and the OPC UA server alike).
:class:`GuardBody` sits in front of every handler (pure ASGI): a mutating request without the token is refused
(401) before its body is read, and a body over ``[daemon] max_body_bytes`` (declared or streamed) with 413.
:func:`require_token` is the same check as a route dependency (it also documents the header in the OpenAPI).
See docs/daemon.md.
"""

from __future__ import annotations

import hmac
import ipaddress
import os
from collections.abc import Mapping
from typing import TYPE_CHECKING, Annotated

from fastapi import Header, Request
from starlette.exceptions import HTTPException as StarletteHTTPException
from tandemscan.daemon.api.errors import problem
from tandemscan.daemon.api.facade import facade_of

if TYPE_CHECKING:
    from tandemscan.config import CellConfig

TOKEN_ENV = "TANDEMSCAN_API_TOKEN"
UNAUTHORISED_HEADERS = {"WWW-Authenticate": 'Bearer realm="tandemscan"'}


class BindRefused(Exception):
    """The daemon was asked to listen beyond loopback without an API token."""


def resolve_token(config: CellConfig, environ: Mapping[str, str] | None = None) -> str | None:
    """The API token: the environment wins over the config; empty means none."""
    env = os.environ if environ is None else environ
    return env.get(TOKEN_ENV) or config.daemon.api_token or None


def check_bind(host: str, token: str | None) -> None:
    """Refuse (:class:`BindRefused`) to listen beyond loopback without a token."""
    if token:
        return
    try:
        loopback = host == "localhost" or ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        loopback = False
    if not loopback:
        raise BindRefused(f"refusing to listen on {host} without an API token: set {TOKEN_ENV} "
                          f"or daemon.api_token in the config, or bind to 127.0.0.1")


def require_token(request: Request, authorization: Annotated[str | None, Header()] = None) -> None:
    """Refuse (401) a caller without the daemon's bearer token, when the daemon has one."""
    token = facade_of(request).token
    if token is not None and not bearer_ok(authorization, token):
        raise StarletteHTTPException(401, "a valid bearer token is required for this call",
                                     headers=UNAUTHORISED_HEADERS)


def bearer_ok(authorization: str | None, token: str) -> bool:
    """Whether an ``Authorization`` header carries ``token`` as its bearer token (constant-time compare)."""
    scheme, _, given = (authorization or "").partition(" ")
    return scheme.lower() == "bearer" and hmac.compare_digest(given.strip().encode(), token.encode())


class GuardBody:
    """ASGI middleware: token of mutating calls first, then the body limit (``max_body_bytes``)."""

    def __init__(self, app, token: str | None, max_body_bytes: int):
        self.app, self.token, self.max_body_bytes = app, token, max_body_bytes

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", ())}
        if self.token is not None and scope["method"] not in ("GET", "HEAD", "OPTIONS") \
                and not bearer_ok(headers.get("authorization"), self.token):
            return await problem(401, "Unauthorized", "a valid bearer token is required for this call", scope["path"],
                                 headers=UNAUTHORISED_HEADERS)(scope, receive, send)
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
