"""What the end of a job (correction, report, exports) needs of its runner, as one picklable object.

The runner's heavy end-of-job work runs where its world map lives: in a worker process in the daemon
(:class:`tandemscan.daemon.stitcher.ProcessWorldMap`), in a thread for ``tandemscan measure``. A
:class:`JobSnapshot` carries the job's small state there (scan records with their poses, transfers, config,
plan, mounts and, on the simulated cell, the ground truth); ``worldmap`` is set to the map on that side.
Frames: poses ``T_W_S`` in the job's world frame W (mm).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from tandemscan.config.models import CellConfig
from tandemscan.pipeline.installation import Installation
from tandemscan.pipeline.plan import Plan

if TYPE_CHECKING:
    from tandemscan.daemon.runner import ScanRecord
    from tandemscan.sim_drivers.world import GroundTruth


@dataclass
class JobSnapshot:
    """A job's state for its end-of-job work; ``world`` is None on a real cell."""

    job_dir: Path
    plan: Plan
    config: CellConfig
    installation: Installation
    scans: list[ScanRecord]
    transfers: list[dict]
    correction: dict
    world: GroundTruth | None
    worldmap: Any = field(default=None, repr=False)  # the VoxelMap where the work runs
    relocalisation: dict = field(default_factory=dict)  # the runner's AGV relocalisation log (report section)

    def __getstate__(self) -> dict:
        return self.__dict__ | {"worldmap": None}
