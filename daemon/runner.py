"""The job runner: executes a plan on the cell's devices, stitches every scan into the world, writes results.

Order per DESIGN.md section 5: measure (persist the raw scan, ``T_C_T``, joints and timestamps before anything
else) -> stitch (Eq. 1 into a voxel world map) -> export (``cloud.ply``, ``report.json``). A ``move_tracker``
step is a coordinate transfer (Eq. 2) with the measurement robot standing still. Steps run one at a time, so
the two robots never move together. Heavy numeric work runs in a worker thread, off the event loop.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tandemscan.config.models import CellConfig
from tandemscan.drivers.interfaces import ChassisPose, TrackerReading
from tandemscan.pipeline import frames as F
from tandemscan.pipeline.cloud_io import write_ply
from tandemscan.pipeline.installation import Installation
from tandemscan.pipeline.plan import MoveArm, MoveMeasure, MoveTracker, Plan, Scan
from tandemscan.pipeline.worldmap import VoxelMap
from tandemscan.sim_drivers.cell import Cell

log = logging.getLogger(__name__)


class JobError(Exception):
    """A job could not be run (bad plan for this cell, a device fault, missing calibration)."""


@dataclass(frozen=True)
class JobProgress:
    """Progress of a running job: steps done of total and what is happening now."""

    done: int
    total: int
    message: str


@dataclass
class ScanRecord:
    """One measured pose: the raw data and its world placement (mm). ``T_W_S_true`` only in simulation."""

    index: int
    tracker_station: int
    file: Path
    reading: TrackerReading
    joints_rad: np.ndarray
    T_W_C: np.ndarray
    T_W_S: np.ndarray
    point_count: int
    T_W_S_true: np.ndarray | None = None


@dataclass
class JobResult:
    """What a finished job left behind."""

    job_dir: Path
    cloud_file: Path
    report_file: Path
    report: dict
    scans: list[ScanRecord] = field(default_factory=list)


def installation_for_job(config: CellConfig, cell: Cell) -> Installation:
    """The mount transforms the stitch uses, per ``job.installation_source``."""
    source = config.job.installation_source
    if source == "nominal":
        return Installation.nominal(config.installation)
    if source == "truth":
        if cell.world is None:
            raise JobError("installation_source = 'truth' needs the simulated cell")
        return cell.world.truth
    path = config.job.calibration_file
    if path is None or not Path(path).is_file():
        raise JobError(f"installation_source = 'calibration' but no calibration file at {path}")
    return Installation.load(path)


def _fsync_write_npz(path: Path, **arrays: np.ndarray) -> None:
    """Write an .npz and make it durable before returning."""
    tmp = path.with_suffix(".tmp")
    with open(tmp, "wb") as fh:
        np.savez(fh, **arrays)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


class JobRunner:
    """Runs one plan on one cell into ``job_dir``."""

    def __init__(
        self,
        cell: Cell,
        plan: Plan,
        config: CellConfig,
        job_dir: Path,
        progress: Callable[[JobProgress], None] | None = None,
    ):
        self.cell = cell
        self.plan = plan
        self.config = config
        self.job_dir = Path(job_dir)
        self.progress = progress or (lambda p: None)
        self.installation = installation_for_job(config, cell)
        self.worldmap = VoxelMap(config.job.voxel_mm)
        self.T_W_C = np.eye(4)  # W is the tracker camera frame at its first station
        self.tracker_station = 0
        self.scans: list[ScanRecord] = []
        self.transfers: list[dict] = []
        self.correction: dict = {"enabled": False}

    async def read_target(self) -> TrackerReading:
        """The target pose at rest, averaged over ``tracker.samples_per_reading`` readings."""
        n = self.config.tracker.samples_per_reading
        readings = [await self.cell.tracker.read_pose(self.config.tracker.timeout_s) for _ in range(n)]
        if n == 1:
            return readings[0]
        return TrackerReading(
            F.mean_pose([r.T_C_T for r in readings]),
            np.mean([r.covariance for r in readings], axis=0) / n,
            readings[-1].timestamp_s,
            readings[-1].frame_number,
        )

    async def run(self) -> JobResult:
        """Execute every step, then stitch and export. Raises :class:`JobError` on failure."""
        started = time.monotonic()
        (self.job_dir / "scans").mkdir(parents=True, exist_ok=True)
        total = len(self.plan.steps) + 1
        await self.cell.arm.enable()
        for i, step in enumerate(self.plan.steps):
            self.progress(JobProgress(i, total, self._describe(step)))
            if isinstance(step, MoveTracker):
                await self._transfer(step)
            elif isinstance(step, MoveMeasure):
                pose = ChassisPose(step.x_mm, step.y_mm, step.heading_rad)
                await self.cell.measure_chassis.move_to(pose, self.config.measure_chassis.timeout_s)
            elif isinstance(step, MoveArm):
                await self.cell.arm.move_joints(np.array(step.joints_rad), self.config.arm.timeout_s)
            elif isinstance(step, Scan):
                await self._scan()
        if self.config.deepmerge.enabled and len(self.scans) > 1:
            from tandemscan.daemon.correction import correct_job

            self.progress(JobProgress(total - 1, total, "correcting the stitch (DeepMerge, pose graph)"))
            self.correction = await asyncio.to_thread(correct_job, self)
        self.progress(JobProgress(total - 1, total, "writing cloud and report"))
        result = await asyncio.to_thread(self._export, time.monotonic() - started)
        self.progress(JobProgress(total, total, "done"))
        return result

    @staticmethod
    def _describe(step) -> str:
        return {
            "move_tracker": "coordinate transfer: moving the tracking robot",
            "move_measure": "moving the measurement robot",
            "move_arm": "moving the arm",
            "scan": "scanning",
        }[step.kind]

    async def _transfer(self, step: MoveTracker) -> None:
        """Eq. 2: read the still target, move the tracker, read it again, re-place the tracker in W."""
        before = await self.read_target()
        await self.cell.tracking_chassis.move_to(
            ChassisPose(step.x_mm, step.y_mm, step.heading_rad), self.config.tracking_chassis.timeout_s
        )
        after = await self.read_target()
        self.T_W_C = F.coordinate_transfer(self.T_W_C, before.T_C_T, after.T_C_T)
        self.tracker_station += 1
        entry = {"station": self.tracker_station, "after_scan": len(self.scans)}
        if self.cell.world is not None:
            err_mm, err_rad = F.pose_error(self.T_W_C, self.cell.world.T_W_F @ self.cell.world.T_F_C())
            entry |= {"tracker_pose_err_mm": err_mm, "tracker_pose_err_deg": float(np.degrees(err_rad))}
        self.transfers.append(entry)
        log.info("coordinate transfer", extra={"station": self.tracker_station})

    async def _scan(self) -> None:
        """Capture and read at rest, persist raw data first, then stitch into the world map."""
        frame = await self.cell.scanner.capture(self.config.scanner.timeout_s)
        reading = await self.read_target()
        joints = await self.cell.arm.joints()
        index = len(self.scans)
        file = self.job_dir / "scans" / f"scan-{index:04d}.npz"
        arrays = {
            "points_S_mm": frame.points_mm.astype(np.float32),
            "T_C_T": reading.T_C_T,
            "tracker_covariance": reading.covariance,
            "joints_rad": joints,
            "scan_timestamp_s": np.array(frame.timestamp_s),
            "tracker_timestamp_s": np.array(reading.timestamp_s),
            "T_W_C": self.T_W_C,
        }
        if frame.normals is not None:
            arrays["normals_S"] = frame.normals.astype(np.float32)
        await asyncio.to_thread(_fsync_write_npz, file, **arrays)
        T_W_S = F.compose(self.T_W_C, reading.T_C_T, self.installation.T_T_S)
        truth = self.cell.world.T_W_S() if self.cell.world is not None else None
        record = ScanRecord(index, self.tracker_station, file, reading, joints, self.T_W_C.copy(), T_W_S,
                            len(frame.points_mm), truth)
        self.scans.append(record)
        await asyncio.to_thread(self._stitch, T_W_S, frame.points_mm, frame.normals)

    def _stitch(self, T_W_S: np.ndarray, points_S: np.ndarray, normals_S: np.ndarray | None) -> None:
        """Eq. 1 into the world map."""
        normals = None if normals_S is None else F.rotate_vectors(T_W_S, normals_S)
        self.worldmap.add(F.transform_points(T_W_S, points_S), normals)

    def _export(self, seconds: float) -> JobResult:
        from tandemscan.daemon.job_outputs import write_job_outputs
        from tandemscan.daemon.report import build_report  # report knows the scoring; runner knows the job

        cloud_file = self.job_dir / "cloud.ply"
        write_ply(cloud_file, self.worldmap.points(), self.worldmap.normals())
        report = build_report(self, seconds)
        report["inspection"] = write_job_outputs(self, report)  # report.html, E57, pose log
        report_file = self.job_dir / "report.json"
        report_file.write_text(json.dumps(report, indent=1), encoding="utf-8")
        return JobResult(self.job_dir, cloud_file, report_file, report, self.scans)
