"""``report.json`` of a measured job as one frozen, typed model, built once at the end of the job and written once
(docs/end-of-job.md, "report.json").

:class:`JobReport` holds the stages' results: the job's figures and scan log (poses ``T_W_S`` in the job's world
frame W, 4x4, mm), the correction, inspection and coverage sections as those stages return them, the job's
resources and timings (s), and two sections beside the product's: the simulator's ground-truth scores
(:class:`GroundTruth`, from the job's observer; None on a real cell) and the resumes a journaled job went
through (:class:`JobHistory`; None for a job run without a journal). :meth:`JobReport.to_json` is the file's
content; :func:`write_job_report` is the one writer of the file (durable: temporary name, fsync, rename). The
observer scores the job after the report is written: its section goes beside it, :func:`write_ground_truth`
(``ground_truth.json``).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tandemscan.pipeline.io.durable import write_durably

REPORT_FILE = "report.json"
GROUND_TRUTH_FILE = "ground_truth.json"  # the simulator's observer's scores, beside it

#: a 4x4 pose (mm) as the report keeps it: rows of floats
Matrix = tuple[tuple[float, ...], ...]


def as_matrix(T: np.ndarray | Sequence[Sequence[float]]) -> Matrix:
    """A 4x4 pose (mm) as nested tuples of floats, as :class:`ScanEntry` keeps it."""
    return tuple(tuple(float(v) for v in row) for row in np.asarray(T, float).tolist())


@dataclass(frozen=True)
class ScanEntry:
    """One scan of ``scan_log``: its index and tracker station, its point count, its raw file's name, its final
    pose ``T_W_S`` (W, mm) and, where the correction changed it, its tracker-stitched pose ``T_W_S_tracker``."""

    index: int
    tracker_station: int
    points: int
    file: str
    T_W_S: Matrix
    T_W_S_tracker: Matrix | None = None

    def to_json(self) -> dict:
        out = {"index": self.index, "tracker_station": self.tracker_station, "points": self.points,
               "file": self.file, "T_W_S": [list(r) for r in self.T_W_S]}
        if self.T_W_S_tracker is not None:
            out["T_W_S_tracker"] = [list(r) for r in self.T_W_S_tracker]
        return out


@dataclass(frozen=True)
class Timings:
    """``timings``: seconds from the last step's commit until report.html and every export were written
    (``after_last_scan_s``), the correction's CPU seconds after the last scan and the seconds of each stage."""

    after_last_scan_s: float
    correction_cpu_s: float | None
    stages_s: Mapping[str, float]

    def to_json(self) -> dict:
        return {"after_last_scan_s": self.after_last_scan_s, "correction_cpu_s": self.correction_cpu_s,
                "stages_s": dict(self.stages_s)}


@dataclass(frozen=True)
class GroundTruth:
    """The simulated cell's scores of the job against its truth (the job's observer, ``daemon.cell.observer``): the
    final stitch's (``ground_truth``, with the seconds the scoring took, ``scoring_s``), the tracker-only stitch's
    summary where the correction changed the poses (``correction.before`` in the report) and the inspection's
    (``ground_truth.inspection``, where it aligned). Written beside ``report.json``, after it, as
    :data:`GROUND_TRUTH_FILE` (:func:`write_ground_truth`)."""

    scores: Mapping[str, Any]
    tracker_only: Mapping[str, Any] | None = None
    inspection: Mapping[str, Any] | None = None

    def section(self) -> dict:
        """The report's ``ground_truth`` section: the scores and, where scored, the inspection's."""
        return dict(self.scores) | ({} if self.inspection is None else {"inspection": dict(self.inspection)})

    def to_json(self) -> dict:
        """The content of :data:`GROUND_TRUTH_FILE`: ``ground_truth`` (:meth:`section`) and, where there is one,
        the tracker-only stitch's summary (``before``)."""
        return {"ground_truth": self.section()} | (
            {} if self.tracker_only is None else {"before": dict(self.tracker_only)})


@dataclass(frozen=True)
class JobHistory:
    """How a journaled job ran: every resume of every attempt (the journal's entries) and the attempts."""

    resumes: tuple[Mapping[str, Any], ...]
    attempts: int


@dataclass(frozen=True)
class JobReport:
    """A measured job's ``report.json`` (mm, deg, s). The correction, inspection, coverage and relocalisation
    sections are the JSON of those stages' results, kept as they return them; ``scans``, ``scans_empty`` and (for
    a journaled job) ``scans_left_out`` are derived from ``scan_log`` and ``relocalisation``."""

    job: str
    plan: str
    transfers: int
    points_raw: int
    points_cloud: int
    voxel_mm: float
    installation_source: str
    seconds: float
    scans_planned: int
    left_out_by_plan: tuple[Mapping[str, Any], ...]
    transfer_log: tuple[Mapping[str, Any], ...]
    relocalisation: Mapping[str, Any]
    correction: Mapping[str, Any]
    scan_log: tuple[ScanEntry, ...]
    inspection: Mapping[str, Any]
    coverage: Mapping[str, Any]
    peak_rss_gib: float | None
    timings: Timings
    ground_truth: GroundTruth | None = None
    history: JobHistory | None = None
    #: the outputs that could not be written (``cloud_ply``, ``e57``, ``inspection``), each with its error
    failed_outputs: Mapping[str, str] = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict:
        """The content of ``report.json``."""
        correction = dict(self.correction)
        if self.ground_truth is not None and self.ground_truth.tracker_only is not None:
            correction["before"] = dict(self.ground_truth.tracker_only)
        out: dict = {
            "job": self.job, "plan": self.plan, "scans": len(self.scan_log), "transfers": self.transfers,
            "points_raw": self.points_raw, "points_cloud": self.points_cloud, "voxel_mm": self.voxel_mm,
            "installation_source": self.installation_source, "seconds": self.seconds,
            "scans_planned": self.scans_planned, "left_out_by_plan": [dict(a) for a in self.left_out_by_plan],
            "scans_empty": [s.index for s in self.scan_log if s.points == 0],
            "transfer_log": [dict(t) for t in self.transfer_log], "relocalisation": dict(self.relocalisation),
            "correction": correction, "scan_log": [s.to_json() for s in self.scan_log],
            "inspection": dict(self.inspection), "coverage": dict(self.coverage),
            "resources": {"peak_rss_gib": self.peak_rss_gib},
        }
        if self.failed_outputs:
            out["failed_outputs"] = dict(self.failed_outputs)
        if self.ground_truth is not None:
            out["ground_truth"] = self.ground_truth.section()
        out["timings"] = self.timings.to_json()
        if self.history is not None:
            out |= {"resumes": [dict(r) for r in self.history.resumes], "attempts": self.history.attempts,
                    "scans_left_out": self.relocalisation["untracked"]}
        return out


def write_job_report(report: JobReport, job_dir: Path | str) -> Path:
    """Write ``report`` as ``report.json`` into ``job_dir`` durably (readers see the old file or the whole new
    one): the one writer of a job's report. The simulator's observer, which scores the job after its report, is
    not in it (``report.ground_truth`` is None here; :func:`write_ground_truth` writes it beside). Returns the
    file."""
    if report.ground_truth is not None:
        raise ValueError("report.json is written before the observer's scores: they go beside it")
    return _write_json(Path(job_dir) / REPORT_FILE, report.to_json())


def write_ground_truth(truth: GroundTruth, job_dir: Path | str) -> Path:
    """Write the observer's scores as :data:`GROUND_TRUTH_FILE` beside ``report.json`` (durably, once, after the
    report: the operator's report does not wait for the simulator's scoring). Returns the file."""
    return _write_json(Path(job_dir) / GROUND_TRUTH_FILE, truth.to_json())


def _write_json(path: Path, content: dict) -> Path:
    data = json.dumps(content, indent=1).encode()
    write_durably(path, lambda f: f.write(data))
    return path
