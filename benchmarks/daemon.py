"""REST latency, event-loop lag, control-loop jitter and watchdog period while a job ingests scans.

Starts ``tandemscan serve`` as a child process on the simulated cell with the scanner at full resolution
(about 3.2 M points a scan) and a fake systemd notify socket (``WATCHDOG_USEC`` = 200 ms, so a ping is due
every 100 ms), submits the default job, and meanwhile times ``GET /v1/jobs/{id}`` and ``GET /v1/devices``
from this process, until the job ends (correction and exports included) or ``--seconds`` pass. The daemon's
own event-loop lag and 50 Hz control-loop jitter (how late each safety tick starts against its schedule) come
from the histograms in ``/metrics``, differenced between scrapes. Before the job an idle phase measures the
same figures with no job running: on a shared machine that is the floor the load alone sets. Prints one
JSON object (ms) on its last line, with the machine's 1-minute load average before and after.

With ``--opcua-subscribers N`` the daemon also serves OPC UA (docs/opcua.md) and N sessions of
``benchmarks/opcua_subscribers.py`` (another process) follow the job's progress, state and the latch for the whole
run, idle phase included: the same figures with OPC UA beside REST.

    nice python benchmarks/daemon.py [--seconds 600] [--idle-seconds 30] [--resolution full|coarse] [--keep-state]
                                     [--opcua-subscribers 20]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
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
from clean_exit import clean_exit_on_sigterm
from results import publish
from tandemscan.sim_drivers.cell import with_surveyed_mounts_toml
from tandemscan.sim_drivers.hil_box import free_port

TOKEN = "bench"
WATCHDOG_USEC = 200_000


def _buckets(text: str, name: str) -> list[tuple[float, float]]:
    """(upper bound s, cumulative count) of a Prometheus histogram in ``text``, in bound order."""
    out = []
    for line in text.splitlines():
        if line.startswith(name + "_bucket{"):
            le = line.split('le="', 1)[1].split('"', 1)[0]
            out.append((float("inf") if le == "+Inf" else float(le), float(line.rsplit(" ", 1)[1])))
    return sorted(out)


def _hist_p99_ms(before: str, after: str, name: str) -> float:
    """p99 (ms) of the observations between two scrapes, interpolated within its bucket (as Prometheus'
    ``histogram_quantile``); past the last finite bound it is that bound."""
    a, b = _buckets(before, name), _buckets(after, name)
    counts = [(le, cb - ca) for (le, cb), (_, ca) in zip(b, a, strict=True)]
    total = counts[-1][1]
    if total == 0:
        return float("nan")
    rank, lower, below = 0.99 * total, 0.0, 0.0
    for le, cum in counts:
        if cum >= rank:
            if le == float("inf"):
                return round(lower * 1000, 3)
            return round((lower + (le - lower) * (rank - below) / max(cum - below, 1e-12)) * 1000, 3)
        lower, below = le, cum
    return round(lower * 1000, 3)


def _pct(values, q) -> float:
    return round(float(np.percentile(values, q)), 3) if len(values) else float("nan")


def _figures(lat: dict[str, list[float]], before: str, after: str, pings: list[float]) -> dict:
    """The figures (ms) of one phase: REST p50/p99 per call, loop lag, control jitter, watchdog period."""
    out = {}
    for kind, values in lat.items():
        out |= {f"rest_get_{kind}_p50_ms": _pct(values, 50), f"rest_get_{kind}_p99_ms": _pct(values, 99)}
    return out | {
        "event_loop_lag_p99_ms": _hist_p99_ms(before, after, "tandemscan_event_loop_lag_seconds"),
        "control_loop_50hz_jitter_p99_ms": _hist_p99_ms(before, after, "tandemscan_control_lateness_seconds"),
        "watchdog_ping_period_p99_ms": _pct(np.diff(pings) * 1000, 99),
    }


class OpcuaLoad:
    """The OPC UA side of a run: a viewer user and a trusted client certificate for the daemon's state folder
    under ``tmp``, and ``n`` subscribed sessions in a child process (``opcua_subscribers.py``)."""

    def __init__(self, tmp: Path, n: int):
        from tandemscan.daemon.api.opcua.security import hash_password, make_application_identity

        self.tmp, self.n, self.port, self.password = tmp, n, free_port(), "bench-pw"
        self.hash = hash_password(self.password)
        self.identity = make_application_identity(tmp / "clients", "bench", "urn:tandemscan:bench-client",
                                                  ["localhost"], server=False, days=2)
        trusted = tmp / "state" / "opcua" / "trusted"
        trusted.mkdir(parents=True)
        shutil.copy(self.identity.certificate, trusted / "bench.der")
        self.proc: subprocess.Popen | None = None

    def config_toml(self) -> str:
        return (f'\n[opcua]\nenabled = true\nport = {self.port}\n[opcua.users.bench]\nrole = "viewer"\n'
                f'password_hash = "{self.hash}"\n')

    def start(self) -> None:
        """Start the subscribers; return once every session subscribed. They run at the lowest CPU priority: in a
        plant the clients are other machines, and on this one their own decoding must not take the daemon's
        cores (the daemon still does all of the server's work)."""
        script = Path(__file__).with_name("opcua_subscribers.py")
        self.proc = subprocess.Popen(
            ["nice", "-n", "19", sys.executable, str(script), f"opc.tcp://127.0.0.1:{self.port}/tandemscan/",
             str(self.identity.certificate), str(self.identity.private_key),
             str(self.tmp / "state" / "opcua" / "own" / "server.der"), "bench", self.password, str(self.n)],
            stdout=subprocess.PIPE, text=True)
        if self.proc.stdout.readline().strip() != "ready":
            raise SystemExit("the OPC UA subscribers did not start")

    def stop(self) -> dict | None:
        """Stop the subscribers; their counts."""
        if self.proc is None:
            return None
        self.proc.terminate()
        out, _ = self.proc.communicate(timeout=120)
        lines = [line for line in out.splitlines() if line.startswith("{")]
        return {"subscribers": self.n, **(json.loads(lines[-1]) if lines else {"errors": "no result"})}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=600.0, help="measure the job at most this long (s)")
    ap.add_argument("--idle-seconds", type=float, default=30.0, help="idle baseline before the job (s)")
    ap.add_argument("--resolution", choices=["full", "coarse"], default="full")
    ap.add_argument("--rate-hz", type=float, default=20.0, help="client request rate")
    ap.add_argument("--keep-state", action="store_true", help="keep the daemon's state folder (GBs of scans)")
    ap.add_argument("--opcua-subscribers", type=int, default=0, help="serve OPC UA with this many subscribed "
                    "sessions (0: OPC UA off)")
    ap.add_argument("--no-publish", action="store_true", help="print the figures only (a run of a series, such "
                    "as opcua_overhead.py's), keeping benchmarks/results/ as it is")
    args = ap.parse_args()

    load_before = os.getloadavg()
    tmp = Path(tempfile.mkdtemp(prefix="tandemscan-bench-"))
    cfg = tmp / "cell.toml"
    cfg.write_text(f'[scanner]\nresolution = "{args.resolution}"\n')
    with_surveyed_mounts_toml(cfg)  # the job stitches with the cell's surveyed mounts, as the README's figures
    opcua = OpcuaLoad(tmp, args.opcua_subscribers) if args.opcua_subscribers else None
    if opcua is not None:
        with open(cfg, "a", encoding="utf-8") as f:
            f.write(opcua.config_toml())
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

    port = free_port()
    url = f"http://127.0.0.1:{port}"
    env = os.environ | {"TANDEMSCAN_STATE_DIR": str(tmp / "state"), "TANDEMSCAN_API_TOKEN": TOKEN,
                        "NOTIFY_SOCKET": str(notify_path), "WATCHDOG_USEC": str(WATCHDOG_USEC)}
    env.pop("WATCHDOG_PID", None)
    log = open(tmp / "daemon.log", "wb")  # noqa: SIM115 - closed below
    proc = subprocess.Popen([sys.executable, "-m", "tandemscan.daemon.cli", "serve", "--port", str(port),
                             "--config", str(cfg)], env=env, stdout=log, stderr=subprocess.STDOUT)
    receiver = threading.Thread(target=receive, daemon=True)
    receiver.start()
    request_errors = 0

    def sample(client: httpx.Client, calls: dict[str, str], lat: dict[str, list[float]]) -> dict:
        nonlocal request_errors
        answers = {}
        for kind, path in calls.items():
            t0 = time.perf_counter()
            try:
                r = client.get(path)
            except httpx.TransportError:  # a reset connection is a failed request, reported below
                request_errors += 1
                continue
            lat[kind].append((time.perf_counter() - t0) * 1000)
            answers[kind] = r
        return answers

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
            if opcua is not None:
                opcua.start()
            period = 1.0 / args.rate_hz
            time.sleep(5.0)  # the scan worker builds its scene; first requests build their schemas
            idle_lat: dict[str, list[float]] = {"devices": []}
            m0, t_idle = client.get("/metrics").text, time.monotonic()
            while time.monotonic() < t_idle + args.idle_seconds:
                sample(client, {"devices": "/v1/devices"}, idle_lat)
                time.sleep(period)
            m1, idle_pings = client.get("/metrics").text, [t for t in pings if t >= t_idle]
            job = client.post("/v1/jobs", json={}, headers={"Authorization": f"Bearer {TOKEN}"}).json()
            t_start = time.monotonic()
            lat: dict[str, list[float]] = {"job": [], "devices": []}
            state = job["state"]
            while time.monotonic() < t_start + args.seconds and state not in ("succeeded", "failed", "cancelled"):
                answers = sample(client, {"job": f"/v1/jobs/{job['id']}", "devices": "/v1/devices"}, lat)
                if "job" in answers:
                    state = answers["job"].json()["state"]
                time.sleep(period)
            seconds = time.monotonic() - t_start
            m2 = client.get("/metrics").text
            final = client.get(f"/v1/jobs/{job['id']}").json()
            if final["state"] not in ("succeeded", "failed", "cancelled"):
                client.post(f"/v1/jobs/{job['id']}/cancel", headers={"Authorization": f"Bearer {TOKEN}"})
    finally:
        opcua_figures = opcua.stop() if opcua is not None else None
        proc.terminate()
        proc.wait(60)
        stop.set()
        receiver.join(2)
        log.close()
    job_pings = [t for t in pings if t_start <= t <= t_start + seconds]
    with sqlite3.connect(tmp / "state" / "journal.sqlite") as db:
        scans = db.execute("SELECT COUNT(*) FROM scans").fetchone()[0]
    if not args.keep_state:
        shutil.rmtree(tmp, ignore_errors=True)
    name = "daemon" if args.resolution == "full" else "daemon-coarse"
    figures = {
        "benchmark": "daemon",
        "scanner_resolution": args.resolution,
        "scans_ingested": scans,
        "steps_done": final["steps_done"],
        "job_state": final["state"],
        "seconds": round(seconds, 1),
        "requests": len(lat["job"]) + len(lat["devices"]),
        "request_errors": request_errors,
        **_figures(lat, m1, m2, job_pings),
        "watchdog_ping_period_target_ms": WATCHDOG_USEC / 2000,
        "idle_baseline": {"seconds": args.idle_seconds, **_figures(idle_lat, m0, m1, idle_pings)},
        "opcua": opcua_figures,
        "cpu_cores": os.cpu_count(),
        "load_average_1min_before_after": [round(load_before[0], 2), round(os.getloadavg()[0], 2)],
    }
    if args.no_publish:
        print(json.dumps(figures), flush=True)
    else:
        publish(name + ("-opcua" if opcua is not None else ""), figures)


if __name__ == "__main__":
    clean_exit_on_sigterm()
    main()
