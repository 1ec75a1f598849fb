"""What OPC UA costs the daemon: REST p99 and the 50 Hz control loop's jitter with and without 20 OPC UA subscribers.

Runs ``benchmarks/daemon.py`` (the default job on the simulated cell, coarse scanner) ``--repeat`` times with OPC UA
off and as often with ``--opcua-subscribers N`` on (secure sessions subscribed to the job's progress, state, step,
the latch and the moving robot: docs/opcua.md), alternating off and on so that a drift of the machine's load falls
on both. Each figure is the median over the runs of a side; ``ratio`` is on / off and ``within_10_percent`` says
whether on is at most 10 % above off for every figure (issue 46's line). One run's p99 rests on a few hundred
requests, so a single pair of runs says little: take at least three of each on an idle machine. Prints one JSON object
on its last line and keeps it as ``benchmarks/results/opcua_overhead.json``.

    python benchmarks/opcua_overhead.py [--repeat 3] [--subscribers 20] [--rate-hz 40]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

from clean_exit import clean_exit_on_sigterm
from results import publish

#: the figures compared (ms), as benchmarks/daemon.py prints them for the job phase
FIGURES = ("rest_get_job_p99_ms", "rest_get_devices_p99_ms", "event_loop_lag_p99_ms",
           "control_loop_50hz_jitter_p99_ms")


def run_daemon_benchmark(subscribers: int, rate_hz: float) -> dict:
    """One run of benchmarks/daemon.py (coarse scanner, the whole default job); its figures."""
    script = Path(__file__).with_name("daemon.py")
    out = subprocess.run([sys.executable, str(script), "--resolution", "coarse", "--seconds", "300",
                          "--idle-seconds", "10", "--rate-hz", str(rate_hz), "--opcua-subscribers",
                          str(subscribers), "--no-publish"], capture_output=True, text=True, check=True).stdout
    figures = json.loads(out.strip().splitlines()[-1])
    if figures["job_state"] != "succeeded" or figures["request_errors"]:
        raise SystemExit(f"a daemon run did not end cleanly: {figures}")
    return figures


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=3, help="runs with OPC UA off, and as many with it on")
    ap.add_argument("--subscribers", type=int, default=20, help="OPC UA sessions during the runs with it on")
    ap.add_argument("--rate-hz", type=float, default=40.0, help="REST request rate of the probing client")
    args = ap.parse_args()
    load_before = os.getloadavg()[0]
    runs: dict[str, list[dict]] = {"off": [], "on": []}
    for _ in range(args.repeat):
        runs["off"].append(run_daemon_benchmark(0, args.rate_hz))
        runs["on"].append(run_daemon_benchmark(args.subscribers, args.rate_hz))
    median = {side: {f: round(statistics.median(r[f] for r in rs), 3) for f in FIGURES} for side, rs in runs.items()}
    ratio = {f: round(median["on"][f] / median["off"][f], 3) for f in FIGURES}
    publish("opcua_overhead", {
        "benchmark": "opcua_overhead",
        "runs_per_side": args.repeat,
        "subscribers": args.subscribers,
        "opcua_off_median": median["off"],
        "opcua_on_median": median["on"],
        "ratio_on_off": ratio,
        "within_10_percent": all(r <= 1.10 for r in ratio.values()),
        "per_run": {side: [{f: r[f] for f in (*FIGURES, "seconds", "requests")} for r in rs]
                    for side, rs in runs.items()},
        "opcua_sessions": [r["opcua"] for r in runs["on"]],
        "cpu_cores": os.cpu_count(),
        "load_average_1min_before_after": [round(load_before, 2), round(os.getloadavg()[0], 2)],
    })


if __name__ == "__main__":
    clean_exit_on_sigterm()
    main()
