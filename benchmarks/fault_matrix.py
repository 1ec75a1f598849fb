"""The fault matrix: every fault of the daemon's fault tests (docs/daemon.md, faults) and what it did to the job.

Runs ``tests/hil/test_daemon_faults.py`` and ``tests/e2e/test_daemon_disk_full.py`` (hardware-in-the-loop cell,
faults injected through the emulators; a full tmpfs) and prints, as one JSON object on the last line, a row per fault:
its outcome, the typed reason, how long until the job left ``running`` (s) and the scans of the finished job.

    .venv/bin/python benchmarks/fault_matrix.py
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from clean_exit import clean_exit_on_sigterm
from results import publish

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        rows_file = Path(tmp) / "matrix.jsonl"
        env = dict(os.environ, TANDEMSCAN_FAULT_MATRIX=str(rows_file))
        proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                               "tests/hil/test_daemon_faults.py", "tests/e2e/test_daemon_disk_full.py"],
                              cwd=ROOT, env=env, capture_output=True, text=True)
        rows = [json.loads(line) for line in rows_file.read_text().splitlines()] if rows_file.exists() else []
    summary = proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else ""
    publish("fault_matrix", {"faults": rows, "tests": summary, "all_passed": proc.returncode == 0})


if __name__ == "__main__":
    clean_exit_on_sigterm()
    main()
