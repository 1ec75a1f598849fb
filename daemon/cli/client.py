"""A small client of a running daemon's REST API (the CLI's ``jobs`` and ``job`` verbs use it).

The daemon's URL comes from ``--url`` or ``$TANDEMSCAN_URL`` (default ``http://127.0.0.1:8470``), the token
from ``$TANDEMSCAN_API_TOKEN``.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterator

import httpx
from tandemscan.daemon.job_state import FINAL_STATES

DEFAULT_URL = "http://127.0.0.1:8470"


class ClientError(Exception):
    """The daemon refused a call or cannot be reached; the message is the problem's detail."""


class SseParser:
    """Server-sent events, one line at a time: :meth:`feed` returns ``(kind, data)`` at each ``data:`` line."""

    def __init__(self) -> None:
        self.kind = "message"

    def feed(self, line: str) -> tuple[str, dict] | None:
        if line.startswith("event: "):
            self.kind = line[7:]
        elif line.startswith("data: "):
            return self.kind, json.loads(line[6:])
        return None


class DaemonClient:
    """Blocking client; one method per REST call used by the CLI."""

    def __init__(self, url: str | None = None, token: str | None = None, timeout_s: float = 10.0):
        self.url = (url or os.environ.get("TANDEMSCAN_URL") or DEFAULT_URL).rstrip("/")
        token = token if token is not None else os.environ.get("TANDEMSCAN_API_TOKEN")
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.http = httpx.Client(base_url=self.url, headers=headers, timeout=timeout_s)

    def close(self) -> None:
        self.http.close()

    def __enter__(self) -> DaemonClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _call(self, method: str, path: str, **kw) -> dict:
        try:
            r = self.http.request(method, path, **kw)
        except httpx.HTTPError as e:
            raise ClientError(f"cannot reach the daemon at {self.url}: {e}") from e
        if r.status_code >= 400:
            try:
                body = r.json()
                detail = body.get("detail") or body.get("title")
            except ValueError:
                detail = r.text
            raise ClientError(f"{r.status_code}: {detail}")
        return r.json()

    def jobs(self, states: list[str] | None = None, limit: int = 20) -> dict:
        return self._call("GET", "/v1/jobs", params={"state": states or [], "limit": limit})

    def job(self, job_id: str) -> dict:
        return self._call("GET", f"/v1/jobs/{job_id}")

    def submit(self, plan: str | None = None, label: str | None = None, idempotency_key: str | None = None,
               part_number: str | None = None, serial_number: str | None = None) -> dict:
        body = {k: v for k, v in (("plan", plan), ("label", label), ("part_number", part_number),
                                  ("serial_number", serial_number)) if v is not None}
        headers = {"Idempotency-Key": idempotency_key} if idempotency_key else {}
        return self._call("POST", "/v1/jobs", json=body, headers=headers)

    def action(self, job_id: str, verb: str) -> dict:
        """``cancel``, ``pause`` or ``resume``."""
        return self._call("POST", f"/v1/jobs/{job_id}/{verb}")

    def events(self, job_id: str | None = None, after: int = 0) -> Iterator[tuple[str, dict]]:
        """Server-sent events as ``(kind, data)``, replayed from ``after``; runs until the caller stops."""
        params = {"after": after} | ({"job": job_id} if job_id else {})
        try:
            with self.http.stream("GET", "/v1/events", params=params, timeout=None) as r:
                parser = SseParser()
                for line in r.iter_lines():
                    if (event := parser.feed(line)) is not None:
                        yield event
        except httpx.HTTPError as e:
            raise ClientError(f"event stream from {self.url} broke: {e}") from e

    def watch(self, job_id: str, on_progress: Callable[[float, dict], None]) -> dict:
        """Follow a job's events until it ends; ``on_progress(percent, job)``; returns the final job."""
        job = self.job(job_id)
        on_progress(job["progress"], job)
        if job["state"] in FINAL_STATES:
            return job
        for kind, data in self.events(job_id):
            if kind == "progress":
                on_progress(data["progress"], job)
            elif kind == "state":
                job = self.job(job_id)
                on_progress(job["progress"], job)
                if data["state"] in FINAL_STATES:
                    return job
        return self.job(job_id)
