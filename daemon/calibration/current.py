"""The cell's current calibration and where a job's mounts came from (docs/calibration.md, "The current
calibration"; docs/verdict.md, "Verdict").

``tandemscan calibrate`` writes the cell's current calibration to ``[calibration] output_file`` with the date it
was made and a fingerprint of the cell configuration it was made for (:func:`cell_fingerprint`: the devices, the
mounts' nominal values and, on the simulated cell, the simulated world). A job configured with ``[job]
installation_source = "current"`` uses it while the fingerprint matches and it is younger than ``[calibration]
max_age_h``, else the nominal mounts (:func:`resolve_installation`); the report names the source, the file and
the date beside the verdict, or why the current calibration was not used (:func:`installation_record`).
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
from pathlib import Path
from typing import TYPE_CHECKING

from tandemscan.pipeline.stitching.installation import Installation

if TYPE_CHECKING:
    from tandemscan.config.models import CellConfig

#: the sections of the cell configuration a calibration holds for: a change to any of them needs a new one
CELL_SECTIONS = ("installation", "scanner", "tracker", "arm", "lift", "measure_chassis", "tracking_chassis", "sim")


def cell_fingerprint(config: CellConfig) -> str:
    """A short hash of the cell configuration's :data:`CELL_SECTIONS` (and the calibration plate's layout)."""
    data = config.model_dump(mode="json", include=set(CELL_SECTIONS))
    data["plate"] = config.calibration.model_dump(mode="json", exclude={"output_file", "max_age_h"})
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode("utf-8")).hexdigest()[:16]


def _created(path: Path, data: dict) -> dt.datetime:
    stamp = data.get("created_utc")
    if stamp:
        return dt.datetime.fromisoformat(stamp)
    return dt.datetime.fromtimestamp(path.stat().st_mtime, dt.UTC)


def current_calibration(config: CellConfig, now: dt.datetime | None = None) -> tuple[Path | None, str]:
    """The cell's current calibration file where it holds for ``config`` now, else None; and why not (or "")."""
    path = Path(config.calibration.output_file)
    if not path.is_file():
        return None, f"no current calibration at {path} (run `tandemscan calibrate`)"
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        created = _created(path, data)
    except (OSError, ValueError) as e:
        return None, f"the current calibration {path} is unreadable: {e}"
    if data.get("made_for") != cell_fingerprint(config):
        return None, f"the current calibration {path} was made for another cell configuration"
    age_h = ((now or dt.datetime.now(dt.UTC)) - created).total_seconds() / 3600.0
    if age_h > config.calibration.max_age_h:
        return None, (f"the current calibration {path} expired: {age_h:.0f} h old, more than "
                      f"{config.calibration.max_age_h:g} h")
    return path, ""


def resolve_installation(config: CellConfig) -> CellConfig:
    """``config`` with ``[job] installation_source = "current"`` resolved: "calibration" with the current
    calibration's file where it holds, else "nominal"; other sources as they are."""
    if config.job.installation_source != "current":
        return config
    path, _ = current_calibration(config)
    job = config.job.model_copy(update={"installation_source": "calibration", "calibration_file": path}
                                if path is not None else {"installation_source": "nominal"})
    return config.model_copy(update={"job": job})


def installation_record(config: CellConfig) -> dict:
    """``{"source", "file", "date"}`` of the mounts a job configured by ``config`` stitches with; on nominal
    mounts ``note``: why no calibration was used."""
    source = config.job.installation_source
    if source in ("nominal", "current"):
        path, why = current_calibration(config)
        if source == "current" and path is not None:
            return installation_record(resolve_installation(config))
        return {"source": "nominal", "file": None, "date": None,
                "note": why or "the job was configured to stitch with the nominal mounts"}
    path = Path(config.job.calibration_file) if config.job.calibration_file else None
    date = None
    if path is not None and path.is_file():
        try:
            date = _created(path, json.loads(path.read_text(encoding="utf-8"))).isoformat(timespec="seconds")
        except (OSError, ValueError):
            date = None
    return {"source": "calibration", "file": None if path is None else str(path), "date": date}




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
