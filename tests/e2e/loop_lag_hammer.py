"""Child process of tests/e2e/test_daemon_loop_lag.py: hammers a daemon's REST handlers a number of rounds.

    python tests/e2e/loop_lag_hammer.py URL JOB_ID ROUNDS

Cycles ``GET /v1/jobs/{id}``, ``GET /v1/jobs?limit=100``, ``GET /v1/devices`` and a replay of the event journal
(``GET /v1/events?after=0``, read until the stream says ``connected``) ``ROUNDS`` times, back to back, from its
own process so that the client's work is not on the daemon's event loop. Prints one JSON object on its last
line: calls per route and the non-2xx answers.
"""

from __future__ import annotations

import json
import sys

import httpx


def _replay(client: httpx.Client) -> int:
    with client.stream("GET", "/v1/events", params={"after": 0}) as r:
        for line in r.iter_lines():
            if line.startswith(": connected"):
                break
        return r.status_code


def main(url: str, job_id: str, rounds: int) -> dict:
    calls = {"job": 0, "jobs": 0, "devices": 0, "events": 0}
    errors: list[str] = []
    requests = {
        "job": lambda c: c.get(f"/v1/jobs/{job_id}").status_code,
        "jobs": lambda c: c.get("/v1/jobs", params={"limit": 100}).status_code,
        "devices": lambda c: c.get("/v1/devices").status_code,
        "events": _replay,
    }
    with httpx.Client(base_url=url, timeout=30) as client:
        for _ in range(rounds):
            for kind, call in requests.items():
                status = call(client)
                calls[kind] += 1
                if status >= 300:
                    errors.append(f"{kind}: {status}")
    return {"calls": calls, "errors": errors[:10]}


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1], sys.argv[2], int(sys.argv[3]))))
