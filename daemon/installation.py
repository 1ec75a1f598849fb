"""Which mount transforms a job stitches with (mm): one resolution for the runner and ``GET /v1/calibration``.

``[job] installation_source`` chooses: ``"nominal"`` (the configured CAD mounts, ``[installation]``),
``"calibration"`` (the file of a calibration job, ``[job] calibration_file``) or ``"truth"`` (the simulated
cell's surveyed mounts, as a perfect calibration file would give them; refused on real drivers). See
docs/calibration.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from tandemscan.config.models import CellConfig
from tandemscan.pipeline.stitching.installation import Installation

if TYPE_CHECKING:
    from tandemscan.daemon.session import CellSession


class InstallationError(Exception):
    """The configured installation source cannot be resolved (no simulated cell, no calibration file)."""


def installation_for_job(config: CellConfig, session: CellSession) -> Installation:
    """The mount transforms (4x4, mm) a job started now on ``session``'s cell stitches with, per
    ``job.installation_source``; :class:`InstallationError` when that source is not available. Reads the
    calibration file when that is the source (blocking: call it off the event loop)."""
    source = config.job.installation_source
    if source == "nominal":
        return Installation.nominal(config.installation)
    if source == "truth":
        sim = session.cell.simulation
        surveyed = None if sim is None else sim.surveyed_installation()
        if surveyed is None:
            raise InstallationError("installation_source = 'truth' needs the simulated cell (twins, not real drivers)")
        return surveyed
    path = config.job.calibration_file
    if path is None or not Path(path).is_file():
        raise InstallationError(f"installation_source = 'calibration' but no calibration file at {path}")
    return Installation.load(path)
