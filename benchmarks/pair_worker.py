"""CPU of the pair worker and of the correction after the last scan, replayed on a finished job's folder; prints one
JSON object last (docs/pairs-while-measuring.md).

The job folder is only read: ``report.json`` (each scan's file, tracker station and tracker pose ``T_W_S_tracker``
or, where the correction left it, ``T_W_S``; the transfers' priors; the voxel) and ``scans/scan-NNNN.npz`` (S, mm;
``T_W_C``, ``T_C_T`` and the reading's covariance, from which the scan's covariance). Each scan's copy thinned at
the voxel (``raw_scan.thin_scan``, as the map hands it over) goes through ``online_pairs.OnlinePairs.add`` in scan
order, as the pair worker takes them (here on this process, one scan after the other: no waiting for the robots),
then ``correction.correct_scans`` takes what it computed, as the end of the job does (without the mount prior:
the figures are seconds, not poses). The ``[correction]`` section is the default configuration's, with
``--check-partners`` where given.

Figures: ``pairs_registered`` while measuring, ``worker_cpu_s`` (this process while the scans went through),
``pair_cpu_s`` (the registrations' own threads), ``cpu_s_a_pair`` and the rest of the worker (the joint
refinement's preparation and association, the selection, the thinning), then the correction's CPU and wall
seconds a stage (``end_cpu_s``, ``end_stage_s``). CPU seconds are the steady figure on a shared machine; run it
with ``nice -n 10`` there and read the seconds as upper bounds.

Usage: nice -n 10 python benchmarks/pair_worker.py JOB_DIR [--scans N] [--check-partners K]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from results import publish
from tandemscan.config import load_config
from tandemscan.daemon.jobs.pose_correction import transfer_priors
from tandemscan.pipeline.geometry.frames import invert
from tandemscan.pipeline.geometry.uncertainty import scan_pose_covariance
from tandemscan.pipeline.io.raw_scan import thin_scan
from tandemscan.pipeline.registration.correction import CorrectionSettings, StitchedJob, StitchedScan, correct_scans
from tandemscan.pipeline.registration.online_pairs import OnlinePairs


def stitched(folder: Path, report: dict, count: int | None) -> list[StitchedScan]:
    """The job's first ``count`` scans (all where None) as the pair worker gets them: thinned copy (S, mm),
    tracker pose, its covariance, station and file."""
    out = []
    for entry in report["scan_log"][:count]:
        with np.load(folder / "scans" / entry["file"]) as raw:
            T_W_S = np.array(entry.get("T_W_S_tracker", entry["T_W_S"]))
            T_T_S = invert(raw["T_W_C"] @ raw["T_C_T"]) @ T_W_S  # the mount the job stitched with
            cov = scan_pose_covariance(raw["T_W_C"], raw["T_C_T"], T_T_S, raw["tracker_covariance"])
            copy = thin_scan(raw["points_S_mm"], report["voxel_mm"])
        out.append(StitchedScan(np.asarray(copy, float), T_W_S, cov, entry["tracker_station"], entry["file"]))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("job", type=Path, help="a finished job's folder (report.json, scans/)")
    parser.add_argument("--scans", type=int, default=None, help="only the first N scans")
    parser.add_argument("--check-partners", type=int, default=None, help="[correction] check_partners_per_scan")
    args = parser.parse_args()
    report = json.loads((args.job / "report.json").read_text(encoding="utf-8"))
    section = load_config(None).correction
    if args.check_partners is not None:
        section = section.model_copy(update={"check_partners_per_scan": args.check_partners})
    cfg = CorrectionSettings.from_section(section)
    scans = stitched(args.job, report, args.scans)
    stations = {s.station for s in scans}
    transfers = [t for t in transfer_priors(report["transfer_log"]) if t.station in stations]

    cpu = time.process_time()
    online = OnlinePairs(cfg, report["voxel_mm"])
    for s in scans:
        online.add(s.points_S, s.T_W_S, s.covariance, s.station, [t for t in transfers if t.station <= s.station])
    work = online.work()
    worker_cpu_s = time.process_time() - cpu
    pairs = len(work.pairs)
    cpu, wall = time.process_time(), time.perf_counter()
    result = correct_scans(StitchedJob(scans, transfers, None, report["voxel_mm"]), cfg, online=work)
    figures = {
        "scans": len(scans), "check_partners_per_scan": cfg.check_partners_per_scan, "pairs_registered": pairs,
        "worker_cpu_s": round(worker_cpu_s, 2), "pair_cpu_s": round(work.pair_cpu_s, 2),
        "cpu_s_a_pair": round(work.pair_cpu_s / pairs, 4) if pairs else None,
        "worker_rest_cpu_s": round(worker_cpu_s - work.pair_cpu_s, 2),
        "end_cpu_s": round(time.process_time() - cpu, 2), "end_wall_s": round(time.perf_counter() - wall, 2),
        "end_stage_s": result.report["stage_seconds"], "pairs_at_end": result.report["pairs"],
        "joint_pairs": result.report["joint"]["pairs"] if "joint" in result.report else None,
    }
    publish("pair_worker", figures)


if __name__ == "__main__":
    main()
