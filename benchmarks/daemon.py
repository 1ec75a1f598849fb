"""REST latency, event-loop lag, control-loop jitter and watchdog period while a job ingests scans.

Starts ``tandemscan serve`` as a child process on the simulated cell with the scanner at full resolution
(about 3.2 M points a scan) and a fake systemd notify socket (``WATCHDOG_USEC`` = 200 ms, so a ping is due
every 100 ms), submits the default job, and meanwhile times ``GET /v1/jobs/{id}`` and ``GET /v1/devices``
from this process, until the job ends (correction and exports included). The daemon's own event-loop lag
and 50 Hz control-loop jitter (how late each safety tick starts against its schedule) come from
``/metrics``. Prints one JSON object (ms) on its last line, with the machine's load average before and after.

    nice python benchmarks/daemon.py [--seconds 600] [--resolution full|coarse]
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

TOKEN = "bench"
WATCHDOG_USEC = 200_000


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _metric(text: str, name: str) -> float:
    for line in text.splitlines():
        if line.startswith(name + " "):
            return float(line.split()[1])
    raise KeyError(name)


def _pct(values, q) -> float:
    return round(float(np.percentile(values, q)), 3) if len(values) else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=600.0, help="measure at most this long (s)")
    ap.add_argument("--resolution", choices=["full", "coarse"], default="full")
    ap.add_argument("--rate-hz", type=float, default=20.0, help="client request rate")
    args = ap.parse_args()

    load_before = os.getloadavg()
    tmp = Path(tempfile.mkdtemp(prefix="tandemscan-bench-"))
    cfg = tmp / "cell.toml"
    cfg.write_text(f'[scanner]\nresolution = "{args.resolution}"\n')
    notify_path = tmp / "notify.sock"
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(notify_path))
    notify.settimeout(0.5)
    pings: list[float] = []
    stop = threading.Event()

    def receive() -> None:
        while not stop.is_set():
            try:
                msg = notify.recv(4096)
            except TimeoutError:
                continue
            if b"WATCHDOG=1" in msg:
                pings.append(time.monotonic())

    port = _free_port()
    url = f"http://127.0.0.1:{port}"
    env = os.environ | {"TANDEMSCAN_STATE_DIR": str(tmp / "state"), "TANDEMSCAN_API_TOKEN": TOKEN,
                        "NOTIFY_SOCKET": str(notify_path), "WATCHDOG_USEC": str(WATCHDOG_USEC)}
    env.pop("WATCHDOG_PID", None)
    log = open(tmp / "daemon.log", "wb")  # noqa: SIM115 - closed below
    proc = subprocess.Popen([sys.executable, "-m", "tandemscan.daemon.cli", "serve", "--port", str(port),
                             "--config", str(cfg)], env=env, stdout=log, stderr=subprocess.STDOUT)
    receiver = threading.Thread(target=receive, daemon=True)
    receiver.start()
    lat = {"job": [], "devices": []}
    request_errors = 0
    try:
        with httpx.Client(base_url=url, timeout=10) as client:
            deadline = time.monotonic() + 120
            while True:
                try:
                    if client.get("/v1/health").status_code == 200:
                        break
                except httpx.HTTPError:
                    if proc.poll() is not None or time.monotonic() > deadline:
                        raise SystemExit("daemon did not start; see " + str(tmp / "daemon.log")) from None
                time.sleep(0.1)
            job = client.post("/v1/jobs", json={}, headers={"Authorization": f"Bearer {TOKEN}"}).json()
            t_start = time.monotonic()
            t_end = t_start + args.seconds
            period = 1.0 / args.rate_hz
            state = job["state"]
            while time.monotonic() < t_end and state not in ("succeeded", "failed", "cancelled"):
                for kind, path in (("job", f"/v1/jobs/{job['id']}"), ("devices", "/v1/devices")):
                    t0 = time.perf_counter()
                    try:
                        r = client.get(path)
                    except httpx.TransportError:  # a reset connection is a failed request, reported below
                        request_errors += 1
                        continue
                    lat[kind].append((time.perf_counter() - t0) * 1000)
                    if kind == "job":
                        state = r.json()["state"]
                time.sleep(period)
            seconds = time.monotonic() - t_start
            final = client.get(f"/v1/jobs/{job['id']}").json()
            metrics = client.get("/metrics").text
            if final["state"] not in ("succeeded", "failed", "cancelled"):
                client.post(f"/v1/jobs/{job['id']}/cancel", headers={"Authorization": f"Bearer {TOKEN}"})
    finally:
        proc.terminate()
        proc.wait(60)
        stop.set()
        receiver.join(2)
        log.close()
    gaps = np.diff(pings) * 1000
    with sqlite3.connect(tmp / "state" / "journal.sqlite") as db:
        scans = db.execute("SELECT COUNT(*) FROM scans").fetchone()[0]
    print(json.dumps({
        "benchmark": "daemon",
        "scanner_resolution": args.resolution,
        "scans_ingested": scans,
        "steps_done": final["steps_done"],
        "job_state": final["state"],
        "seconds": round(seconds, 1),
        "requests": len(lat["job"]) + len(lat["devices"]),
        "request_errors": request_errors,
        "rest_get_job_p50_ms": _pct(lat["job"], 50),
        "rest_get_job_p99_ms": _pct(lat["job"], 99),
        "rest_get_devices_p50_ms": _pct(lat["devices"], 50),
        "rest_get_devices_p99_ms": _pct(lat["devices"], 99),
        "event_loop_lag_p99_ms": round(_metric(metrics, "tandemscan_event_loop_lag_p99_seconds") * 1000, 3),
        "control_loop_50hz_jitter_p99_ms":
            round(_metric(metrics, "tandemscan_control_lateness_p99_seconds") * 1000, 3),
        "watchdog_ping_period_target_ms": WATCHDOG_USEC / 2000,
        "watchdog_ping_period_p99_ms": _pct(gaps, 99),
        "watchdog_pings": len(pings),
        "cpu_cores": os.cpu_count(),
        "load_average_1min_before_after": [round(load_before[0], 2), round(os.getloadavg()[0], 2)],
    }))


if __name__ == "__main__":
    main()
