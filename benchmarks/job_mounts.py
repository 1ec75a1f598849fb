"""Which mounts a benchmark's job stitches with. The product never reads the simulated cell's true mounts; a
benchmark that measures the correction apart from the calibration's error hands its job the cell's surveyed
mounts as a calibration file (``sim_drivers.cell.with_surveyed_mounts``: exact to 0.1 um), as the figures in
the README were measured. ``--mounts configured`` runs the configuration's own source instead (``nominal``, or a
calibration file from ``tandemscan calibrate``); without ``--mounts`` a configuration that names a calibration
file keeps it, any other gets the surveyed mounts."""

from __future__ import annotations

import argparse
from pathlib import Path

from tandemscan.config.models import CellConfig
from tandemscan.daemon.cell.session import CellSession
from tandemscan.sim_drivers.cell import with_surveyed_mounts


def add_mounts_option(parser: argparse.ArgumentParser) -> None:
    """The ``--mounts surveyed|configured`` option (default: see the module doc)."""
    parser.add_argument("--mounts", choices=["surveyed", "configured"],
                        help="the job's mounts: the simulated cell's surveyed ones or the config's source (default: "
                        "the config's where it names a calibration file, else surveyed)")


def chosen_mounts(config: CellConfig, mounts: str | None) -> str:
    """``"surveyed"`` or ``"configured"``: ``mounts`` as asked, else per the configuration (module doc)."""
    if mounts is not None:
        return mounts
    return "configured" if config.job.installation_source == "calibration" else "surveyed"


def job_config(config: CellConfig, mounts: str, session: CellSession, folder: Path) -> CellConfig:
    """``config`` for a job on ``session``'s simulated cell: with ``mounts == "surveyed"`` its surveyed mounts,
    written into ``folder``; else as it is."""
    return with_surveyed_mounts(config, session.cell.simulation, folder) if mounts == "surveyed" else config
