"""Which mount transforms a job stitches with (mm): one resolution for the runner and ``GET /v1/calibration``.

``[job] installation_source`` chooses: ``"nominal"`` (the configured CAD mounts, ``[installation]``),
``"calibration"`` (the file of a calibration job, ``[job] calibration_file``) or ``"current"`` (the cell's current
calibration where it holds, else nominal: ``calibration_state.resolve_installation``). The simulated cell's true mounts
are never a source: the simulator's truth is for scoring only. See docs/calibration.md.
"""

from __future__ import annotations

from pathlib import Path

from tandemscan.config.models import CellConfig
from tandemscan.daemon.calibration_state import resolve_installation
from tandemscan.pipeline.stitching.installation import Installation


class InstallationError(Exception):
    """The configured installation source cannot be resolved (no calibration file)."""


def installation_for_job(config: CellConfig) -> Installation:
    """The mount transforms (4x4, mm) a job configured by ``config`` stitches with, per
    ``job.installation_source``; :class:`InstallationError` when that source is not available. Reads the
    calibration file when that is the source (blocking: call it off the event loop)."""
    config = resolve_installation(config)
    source = config.job.installation_source
    if source == "nominal":
        return Installation.nominal(config.installation)
    path = config.job.calibration_file
    if path is None or not Path(path).is_file():
        raise InstallationError(f"installation_source = 'calibration' but no calibration file at {path}")
    return Installation.load(path)
