"""Observers of a job: what the simulator's ground-truth scoring subscribes to, and nothing the product reads.

The runner tells its :class:`JobObserver` what it measured (scans, tracker stations, AGV stations); the
observer's scorer (:class:`~tandemscan.daemon.jobs.snapshot.JobScorer`) travels with the job's end-of-job work and
writes the report's ``ground_truth`` section from the final poses and cloud. A real cell has no observer; the simulated
cell's lives in ``sim_drivers`` (``docs/architecture.md``, the cell layer). Frames: W the job's world frame, F the
plan's (part) frame; mm, rad, 4x4 float64.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

import numpy as np

if TYPE_CHECKING:
    from tandemscan.daemon.jobs.snapshot import JobScorer
    from tandemscan.pipeline.stitching.installation import Installation




class JobObserver(Protocol):
    """Hooks the runner calls as it measures; none returns anything the job uses."""

    def world_defined(self) -> None:
        """W became the tracker camera frame where it stands now (job start, a relocation before any scan)."""
        ...

    def scan_measured(self, index: int) -> None:
        """Scan ``index`` was captured where the scanner stands now."""
        ...

    def tracker_transferred(self, station: int, T_W_C: np.ndarray) -> None:
        """The tracker's station ``station`` was placed in W at ``T_W_C`` by a coordinate transfer."""
        ...

    def agv_located(self, step: int, T_F_V2: np.ndarray) -> None:
        """The measurement AGV was located at ``T_F_V2`` after step ``step``."""
        ...

    def scorer(self) -> JobScorer:
        """The scorer of what was observed so far."""
        ...


class CalibrationObserver(Protocol):
    """Hooks of a calibration job."""

    def calibration_started(self) -> None:
        """The calibration is about to scan its plate."""
        ...

    def calibration_scored(self, nominal: Installation, calibrated: Installation) -> dict[str, float] | None:
        """Each mount's error (mm, deg) of the nominal and calibrated installation; None where not scored."""
        ...
