"""Where a benchmark's figures go: one JSON object printed on the last line, and the same object kept with the
date, the code it measured and the arguments in ``benchmarks/results/<name>.json`` (README.md "Figures";
``render_figures.py`` renders README's table from these files)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from datetime import UTC, datetime
from pathlib import Path

RESULTS_DIR = Path(__file__).resolve().parent / "results"


def code_version(repo: Path = RESULTS_DIR.parent.parent) -> str:
    """The short commit id of ``repo``'s HEAD, ``+dirty`` when tracked files differ from it; ``unknown`` outside
    a git checkout."""
    def git(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True, check=False)

    head = git("rev-parse", "--short", "HEAD")
    if head.returncode != 0:
        return "unknown"
    dirty = git("diff", "--quiet", "HEAD").returncode != 0
    return head.stdout.strip() + ("+dirty" if dirty else "")


def publish(name: str, figures: dict, results_dir: Path = RESULTS_DIR) -> Path:
    """Keep ``figures`` as ``results_dir/<name>.json`` (with date, code and arguments) and print them as the
    last line of output. ``name`` says which run it is (a variant, such as ``whole_part-full``, has its own
    file). Returns the file written."""
    record = {"benchmark": name, "date": datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC"),
              "code": code_version(), "argv": sys.argv[1:], "figures": figures}
    results_dir.mkdir(parents=True, exist_ok=True)
    path = results_dir / f"{name}.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp, path)
    print(json.dumps(figures), flush=True)
    return path
