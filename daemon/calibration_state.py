"""Where a job's mounts came from, as its report states it beside the verdict (docs/inspection.md, "Verdict").

The installation a job stitched with is either the configured nominal mounts or a calibration file
(``[job] installation_source``, ``daemon.installation``); the report names the source, the file and the date the
calibration was made (the file's ``created_utc``, else the file's modification time).
"""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path
from typing import TYPE_CHECKING

from tandemscan.pipeline.inspection.verdict import VerdictContext

if TYPE_CHECKING:
    from tandemscan.config.models import CellConfig
    from tandemscan.daemon.snapshot import JobSnapshot


def installation_record(config: CellConfig) -> dict:
    """``{"source", "file", "date"}`` of the mounts a job configured by ``config`` stitches with."""
    source = config.job.installation_source
    if source == "nominal":
        return {"source": "nominal", "file": None, "date": None}
    path = Path(config.job.calibration_file) if config.job.calibration_file else None
    date = None
    if path is not None and path.is_file():
        try:
            date = json.loads(path.read_text(encoding="utf-8")).get("created_utc")
        except (OSError, ValueError):
            date = None
        if date is None:
            date = dt.datetime.fromtimestamp(path.stat().st_mtime, dt.UTC).isoformat(timespec="seconds")
    return {"source": "calibration", "file": None if path is None else str(path), "date": date}


def verdict_context(job: JobSnapshot) -> VerdictContext:
    """What a job's verdict is made in: the installation it stitched with."""
    return VerdictContext(installation=installation_record(job.config))
