"""What the end of a job (correction, report, exports) needs of its runner, as one picklable object.

The runner's heavy end-of-job work runs where its world map lives: in a worker process in the daemon
(:class:`tandemscan.daemon.jobs.stitcher.ProcessWorldMap`), in a thread for ``tandemscan measure``. A
:class:`JobSnapshot` carries the job's small state there (scan records with their poses, transfers, config,
plan, mounts, the world frame W placed in the plan's frame F where it was measured, and on the simulated cell
the ground-truth scorer, :class:`JobScorer`, from the job's observer, :mod:`tandemscan.daemon.cell.observer`);
``worldmap`` is set to the map on that side, and ``scan_copies`` to the scans' thinned copies the map's owner kept.
Frames: poses ``T_W_S`` in the job's world frame W (mm).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from tandemscan.config.models import CellConfig
from tandemscan.pipeline.planning.plan import Plan
from tandemscan.pipeline.stitching.installation import Installation

if TYPE_CHECKING:
    from tandemscan.daemon.jobs.records import ScanRecord
    from tandemscan.pipeline.job_report import JobHistory
    from tandemscan.pipeline.registration.pose_covariance import PoseCovariance


class JobScorer(Protocol):
    """Picklable: scores a job where its world map lives (``job.worldmap`` set)."""

    def score(self, job: JobSnapshot) -> dict:
        """The ``ground_truth`` section for the job's scans at their poses ``T_W_S`` now and its cloud."""
        ...

    def score_inspection(self, job: JobSnapshot, inspection: dict) -> dict:
        """``ground_truth.inspection``: the report's ``inspection`` section (its alignment's ``T_F_W`` and its
        deviation areas) against the truth."""
        ...


@dataclass
class JobSnapshot:
    """A job's state for its end-of-job work; ``scorer`` is None on a real cell, ``T_F_W`` (mm) None where the
    job did not place its world in the plan's frame (relocalisation off or the target never seen)."""

    job_dir: Path
    plan: Plan
    config: CellConfig
    installation: Installation
    scans: list[ScanRecord]
    transfers: list[dict]
    correction: dict
    scorer: JobScorer | None
    T_F_W: np.ndarray | None = None
    worldmap: Any = field(default=None, repr=False)  # the VoxelMap where the work runs
    relocalisation: dict = field(default_factory=dict)  # the runner's AGV relocalisation log (report section)
    pose_covariance: PoseCovariance | None = None  # the final poses' errors jointly (the end of the job sets it)
    history: JobHistory | None = None  # the journal's resumes and attempts (report.json), None without a journal
    # where the work runs: the scans thinned at the map's voxel as they were merged, by file (stitcher.merge_scan)
    scan_copies: dict[str, np.ndarray] | None = field(default=None, repr=False)

    def __getstate__(self) -> dict:
        return self.__dict__ | {"worldmap": None, "scan_copies": None}
