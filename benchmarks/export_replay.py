"""Seconds of a finished job's exports and inspection (``outputs.export_job``: ``cloud.ply``, the E57 and pose log in
their process, the inspection with the points' U and report.html) replayed on what a real job handed it, so that the
same end of a job can be timed again and again (code A against code B on one machine) and its outputs compared.
``inspection_speed.py`` rebuilds a job from its folder instead, without the poses' covariance (no U).

``capture FILE ARGS``: runs ``tandemscan ARGS`` (``make measure``'s job: ``measure --plan out/plan.toml
--calibration out/calibration.json``) and pickles what ``finish`` hands ``export_job`` (the job's snapshot without
its scorer, its cloud, the stitch-view points and the tracker poses) into FILE, about 0.5 GB for the whole part; the
job's scan files must stay where it wrote them (the E57 reads them). ``replay FILE``: ``export_job`` on FILE into a
temporary folder ``--runs`` times: each run's wall and CPU seconds (this process, all its threads; the E57's
process apart) and whether its report section is the first run's. Prints one JSON object last.

Usage, from the repository root (``nice -n 10``; the replay's wall seconds need an idle machine, its CPU seconds
less so):
  .venv/bin/python benchmarks/export_replay.py capture /tmp/export_job.pkl measure --plan out/plan.toml \
      --calibration out/calibration.json
  .venv/bin/python benchmarks/export_replay.py replay /tmp/export_job.pkl --runs 3
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pickle
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path

from clean_exit import clean_exit_on_sigterm
from inspection_speed import _cpu_s
from results import publish
from tandemscan.daemon.jobs import finish
from tandemscan.daemon.jobs.outputs import export_job
from tandemscan.pipeline.compute import LazyBackend


def capture(file: Path, tandemscan_args: list[str]) -> int:
    """``tandemscan tandemscan_args`` with what its end of the job hands ``export_job`` pickled into ``file``."""
    from tandemscan.daemon.cli import main as tandemscan

    def captured(job, points_S=None, tracker_poses=None, *, backend):
        with open(file, "wb") as f:
            pickle.dump({"job": dataclasses.replace(job, scorer=None), "cloud": job.worldmap, "points_S": points_S,
                         "tracker_poses": tracker_poses}, f, protocol=5)
        return export_job(job, points_S, tracker_poses, backend=backend)

    finish.export_job = captured
    return tandemscan(tandemscan_args)


def replay(file: Path, runs: int) -> dict:
    """``export_job`` on the snapshot in ``file``, ``runs`` times, each into a fresh folder of the same name."""
    captured = pickle.loads(file.read_bytes())
    seconds, same, first = [], [], None
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(runs):
            out = Path(tmp) / captured["job"].job_dir.name
            shutil.rmtree(out, ignore_errors=True)
            out.mkdir()
            job = dataclasses.replace(captured["job"], job_dir=out, worldmap=captured["cloud"])
            t, cpu, e57 = time.perf_counter(), _cpu_s(), _cpu_s(resource.RUSAGE_CHILDREN)
            with LazyBackend(job.config.compute) as backend:
                exports = export_job(job, captured["points_S"], captured["tracker_poses"], backend=backend)
            seconds.append({"wall_s": round(time.perf_counter() - t, 3), "cpu_s": round(_cpu_s() - cpu, 3),
                            "e57_process_cpu_s": round(_cpu_s(resource.RUSAGE_CHILDREN) - e57, 3),
                            "load_avg_1min": round(os.getloadavg()[0], 2), "failed": exports.failed})
            section = {k: v for k, v in exports.inspection.items() if k != "created_utc"}
            first = section if first is None else first
            same.append(json.dumps(section, sort_keys=True, default=str) == json.dumps(first, sort_keys=True,
                                                                                         default=str))
    return {"benchmark": "export_replay", "job": captured["job"].job_dir.name, "points": len(captured["cloud"]),
            "scans": len(captured["job"].scans), "runs": seconds, "section_as_first": same,
            "verdict": first.get("verdict") if first else None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    cap = sub.add_parser("capture")
    cap.add_argument("file", type=Path)
    cap.add_argument("tandemscan_args", nargs=argparse.REMAINDER)
    rep = sub.add_parser("replay")
    rep.add_argument("file", type=Path)
    rep.add_argument("--runs", type=int, default=2)
    args = ap.parse_args()
    if args.what == "capture":
        sys.exit(capture(args.file, args.tandemscan_args))
    publish("export_replay", replay(args.file, args.runs))


if __name__ == "__main__":  # the E57's process is spawned: it imports this module without running it
    clean_exit_on_sigterm()
    main()
