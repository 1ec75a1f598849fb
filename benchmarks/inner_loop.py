"""How long the test suite's inner loop takes (docs/testing.md, the inner loop): ``make test-fast``'s selection on
pytest-xdist, wall time and the CPU time of pytest and its workers, with the machine's load before and after.
A figure for the idle machine: on a loaded one the wall time grows with the load, the CPU time much less.

    .venv/bin/python benchmarks/inner_loop.py            # the inner loop (make test-fast)
    .venv/bin/python benchmarks/inner_loop.py --suite    # the whole suite (make test), for comparison
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import subprocess
import sys
import time
from pathlib import Path

from clean_exit import clean_exit_on_sigterm
from results import publish

ROOT = Path(__file__).resolve().parents[1]
#: the Makefile's test-fast selection
INNER_LOOP = "not hil and not browser and not e2e and not slow"


def outcome_counts(summary: str) -> dict[str, int]:
    """pytest's closing line ("3 failed, 626 passed, 1 skipped in 61.2s") as counts by outcome."""
    return {word: int(n) for n, word in re.findall(r"(\d+) (passed|failed|skipped|errors?|deselected)", summary)}


def main() -> None:
    parser = argparse.ArgumentParser(description="Time the inner loop (make test-fast) or the whole suite.")
    parser.add_argument("--suite", action="store_true", help="the whole suite (make test), not the inner loop")
    parser.add_argument("--workers", type=int, default=2, help="pytest-xdist workers (make's TEST_WORKERS)")
    args = parser.parse_args()
    command = [sys.executable, "-m", "pytest", "-q", "-n", str(args.workers), "--dist", "loadfile"]
    if not args.suite:
        command += ["-m", INNER_LOOP]
    load_before = os.getloadavg()[0]
    start = time.perf_counter()
    proc = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
    wall_s = time.perf_counter() - start
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    summary = proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else ""
    publish("inner_loop-suite" if args.suite else "inner_loop", {
        "selection": "all" if args.suite else INNER_LOOP, "workers": args.workers, "wall_s": round(wall_s, 1),
        "cpu_s": round(usage.ru_utime + usage.ru_stime, 1), "tests": outcome_counts(summary),
        "exit_status": proc.returncode, "cpus": os.cpu_count(), "load_1min_before": round(load_before, 2),
        "load_1min_after": round(os.getloadavg()[0], 2)})


if __name__ == "__main__":
    clean_exit_on_sigterm()
    main()
