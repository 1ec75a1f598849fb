"""Each inspected job's characteristics by part number and serial, in the daemon's state folder
(``part_results.sqlite``, beside the journal), and their trend over serials (docs/quality.md, "Serials and trends").

A job with a template records one row per characteristic when its report is written; a trend is the last N
rows of one part number's characteristic in measuring order, with its individuals chart
(:func:`tandemscan.pipeline.inspection.spc.individuals_chart`). Millimetres, times in seconds (UNIX).
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

from tandemscan.config.inspection_template import find_template, load_template
from tandemscan.config.loader import ConfigError
from tandemscan.config.models import CellConfig
from tandemscan.daemon.store.sqlite_db import SqliteDb
from tandemscan.pipeline.inspection.spc import ControlChart, individuals_chart

DB_FILE = "part_results.sqlite"
HISTORY_FILE = "part_history.json"  # the part's earlier results, put in a job's folder before it runs
HISTORY_SERIALS = 30  # serials of each characteristic a job's report looks back on

log = logging.getLogger(__name__)

_SCHEMA = """
CREATE TABLE IF NOT EXISTS characteristic_results (
  seq INTEGER PRIMARY KEY AUTOINCREMENT,
  job_id TEXT NOT NULL,
  part_number TEXT NOT NULL,
  serial TEXT,
  characteristic TEXT NOT NULL,
  name TEXT NOT NULL,
  actual_mm REAL,
  lower_mm REAL NOT NULL,
  upper_mm REAL NOT NULL,
  uncertainty_mm REAL,
  status TEXT NOT NULL,
  measured_s REAL NOT NULL,
  UNIQUE (job_id, characteristic)
);
CREATE INDEX IF NOT EXISTS part_characteristic ON characteristic_results (part_number, characteristic, seq);
"""


@dataclass(frozen=True)
class Measured:
    """One serial's result of a characteristic."""

    job_id: str
    serial: str | None
    measured_s: float
    actual_mm: float | None
    status: str


@dataclass(frozen=True)
class Trend:
    """A characteristic's last results over serials and, where two or more were measured, its chart."""

    part_number: str
    characteristic: str
    name: str
    lower_mm: float
    upper_mm: float
    series: tuple[Measured, ...]
    chart: ControlChart | None


class PartResults:
    """The characteristics' results of the jobs under ``state_dir`` (thread-safe, :mod:`.sqlite_db`)."""

    def __init__(self, state_dir: Path | str):
        self._db = SqliteDb(Path(state_dir) / DB_FILE, _SCHEMA)

    def close(self) -> None:
        self._db.close()

    def record(self, job_id: str, part_number: str, serial: str | None, characteristics: Iterable[Mapping],
               measured_s: float | None = None) -> int:
        """Store a job's characteristics (report.json ``inspection.characteristics``); a job recorded again
        (a resumed job's report) replaces its rows. Returns how many were stored."""
        t = time.time() if measured_s is None else measured_s
        rows = [(job_id, part_number, serial, c["id"], c["name"],
                 c["actual_mm"] if c["actual_mm"] is not None and math.isfinite(c["actual_mm"]) else None,
                 c["lower_mm"], c["upper_mm"],
                 c["uncertainty_mm"] if c["uncertainty_mm"] is not None and math.isfinite(c["uncertainty_mm"])
                 else None, c["status"], t) for c in characteristics]
        with self._db.tx() as conn:
            conn.executemany(
                "INSERT OR REPLACE INTO characteristic_results (job_id, part_number, serial, characteristic, name, "
                "actual_mm, lower_mm, upper_mm, uncertainty_mm, status, measured_s) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)", rows)
        return len(rows)

    def characteristics(self, part_number: str) -> list[str]:
        """The ids of the characteristics recorded for ``part_number``, in the order first recorded."""
        rows = self._db.conn().execute(
            "SELECT characteristic, MIN(seq) AS first FROM characteristic_results WHERE part_number = ? "
            "GROUP BY characteristic ORDER BY first", (part_number,))
        return [r["characteristic"] for r in rows]

    def trend(self, part_number: str, characteristic: str, last: int = 50) -> Trend | None:
        """The last ``last`` results of one characteristic of ``part_number`` in measuring order, with the
        individuals chart of the measured ones against the latest tolerance; None when none is recorded."""
        rows = self._db.conn().execute(
            "SELECT * FROM characteristic_results WHERE part_number = ? AND characteristic = ? "
            "ORDER BY seq DESC LIMIT ?", (part_number, characteristic, last)).fetchall()[::-1]
        if not rows:
            return None
        series = tuple(Measured(r["job_id"], r["serial"], r["measured_s"], r["actual_mm"], r["status"]) for r in rows)
        newest = rows[-1]
        values = [m.actual_mm for m in series if m.actual_mm is not None]
        chart = individuals_chart(values, newest["lower_mm"], newest["upper_mm"]) if values else None
        return Trend(part_number, characteristic, newest["name"], newest["lower_mm"], newest["upper_mm"], series,
                     chart)

    def history(self, part_number: str, last: int = HISTORY_SERIALS) -> dict:
        """JSON-ready: per characteristic of ``part_number`` its last ``last`` results (what a job's report
        draws its trends from, :data:`HISTORY_FILE`)."""
        out = {}
        for cid in self.characteristics(part_number):
            trend = self.trend(part_number, cid, last)
            assert trend is not None
            out[cid] = [{"serial": m.serial, "job": m.job_id, "actual_mm": m.actual_mm, "status": m.status}
                        for m in trend.series]
        return out

    def write_history(self, job_dir: Path, part_number: str) -> Path:
        """Put the part's :meth:`history` into ``job_dir`` (:data:`HISTORY_FILE`) for the job's report."""
        path = Path(job_dir) / HISTORY_FILE
        path.write_text(json.dumps({"part_number": part_number, "characteristics": self.history(part_number)}))
        return path


def prepare_part(config: CellConfig, request: Mapping, job_dir: Path, state_dir: Path) -> CellConfig:
    """A daemon job's configuration with the part's identity from its ``request`` (``part_number``,
    ``serial_number``), and the part's earlier results put in ``job_dir`` for its report (the part number: the
    request's, else its inspection template's; none without either)."""
    job = config.job.model_copy(update={k: v for k, v in (("part_number", request.get("part_number")),
                                                          ("serial", request.get("serial_number"))) if v})
    config = config.model_copy(update={"job": job})
    number = job.part_number
    if number is None:
        found = find_template(config.part.mesh, configured=config.inspection.template)
        try:
            number = None if found is None else load_template(found).part_number
        except ConfigError as e:  # the job measures; its inspection reports the template's error
            log.warning("no part history for the report: %s", e)
    if number is not None:
        results = PartResults(state_dir)
        try:
            results.write_history(job_dir, number)
        finally:
            results.close()
    return config


def record_part(state_dir: Path, job_id: str, report: Mapping) -> int:
    """Store the characteristics of a job's ``report`` (report.json) under its part number and serial;
    0 when it has none."""
    inspection = report.get("inspection") or {}
    part = inspection.get("part") or {}
    if not inspection.get("characteristics") or "part_number" not in part:
        return 0
    results = PartResults(state_dir)
    try:
        return results.record(job_id, part["part_number"], part.get("serial"), inspection["characteristics"])
    finally:
        results.close()
