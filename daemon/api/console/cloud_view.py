"""The thinned, compact binary copy of a finished job's stitched cloud that the console's 3D view draws
(docs/console.md, "3D view").

Source: ``cloud_deviation.ply`` (part frame F, mm, with the signed deviation from CAD per point) when the job
was inspected, else ``cloud.ply`` (world frame W, mm, no deviation). Every k-th point is kept so that at most
``max_points`` remain. The colour scale and tolerance band are the report's (``report.json``, section
``inspection``), so the 3D view and report.html colour a point alike.

Layout (little-endian)::

    4 bytes   magic b"TSV1"
    uint32    length L of the header in bytes (a multiple of 4)
    L bytes   header: UTF-8 JSON padded with spaces (see :class:`CloudView`)
    n*3 f32   x y z per point, mm, relative to ``origin_mm`` (float32 keeps 0.001 mm over a 10 m part)
    n f32     deviation per point, mm (only when ``deviation`` is true)
"""

from __future__ import annotations

import json
import os
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tandemscan.pipeline.io.cloud_io import CloudIOError, read_ply_vertices

MAGIC = b"TSV1"
VIEW_POINTS = 200_000
VIEW_FILE = "console-view.bin"  # cached in the job folder: a finished job's cloud does not change
MEDIA_TYPE = "application/octet-stream"

# The report's deviation colour map, below CAD to above (tandemscan.pipeline.inspection.deviation_maps.DEVIATION_CMAP,
# which this module does not import: that pulls matplotlib and Open3D into the daemon's process).
DEVIATION_COLOURS = ("#1d3fbf", "#20b7e0", "#2fbf4a", "#f2e02a", "#d7261e")


class CloudViewError(Exception):
    """The job's cloud file cannot be read into a view; the message names the file."""


@dataclass(frozen=True)
class CloudView:
    """A thinned cloud: ``points_mm`` (n, 3) float32 relative to ``origin_mm`` in ``frame`` ("F" or "W"),
    ``deviation_mm`` (n,) float32 or None, how many points the full cloud has, and the report's symmetric
    ``colour_scale_mm`` (low, high) and ``tolerance_mm`` (lower, upper), None without an inspection."""

    frame: str
    origin_mm: tuple[float, float, float]
    points_mm: np.ndarray
    deviation_mm: np.ndarray | None
    points_total: int
    colour_scale_mm: tuple[float, float] | None
    tolerance_mm: tuple[float, float] | None

    def header(self) -> dict:
        return {"format": "tandemscan cloud view 1", "units": "mm", "frame": self.frame,
                "origin_mm": list(self.origin_mm), "points": len(self.points_mm), "points_total": self.points_total,
                "deviation": self.deviation_mm is not None,
                "colour_scale_mm": None if self.colour_scale_mm is None else list(self.colour_scale_mm),
                "tolerance_mm": None if self.tolerance_mm is None else list(self.tolerance_mm),
                "colours": list(DEVIATION_COLOURS)}

    def encode(self) -> bytes:
        """The binary layout of the module docstring."""
        head = json.dumps(self.header()).encode()
        head += b" " * (-len(head) % 4)
        parts = [MAGIC, struct.pack("<I", len(head)), head, self.points_mm.astype("<f4").tobytes()]
        if self.deviation_mm is not None:
            parts.append(self.deviation_mm.astype("<f4").tobytes())
        return b"".join(parts)


def build_view(job_dir: Path, report: dict, max_points: int = VIEW_POINTS) -> CloudView:
    """The view of the job in ``job_dir`` whose ``report.json`` is ``report``."""
    inspection = report.get("inspection") or {}
    deviation_file = job_dir / inspection.get("files", {}).get("deviation_ply", "-")
    inspected = "colour_scale_mm" in inspection and deviation_file.is_file()
    try:
        fields = read_ply_vertices(deviation_file if inspected else job_dir / "cloud.ply")
    except CloudIOError as e:
        raise CloudViewError(str(e)) from e
    total = len(fields["x"])
    keep = slice(None, None, max(1, -(-total // max_points)))
    xyz = np.column_stack([fields[a][keep] for a in "xyz"]).astype(np.float64)
    origin = xyz.mean(axis=0) if len(xyz) else np.zeros(3)
    deviation = fields["deviation_mm"][keep].astype(np.float32) if inspected else None
    tolerance = inspection.get("as_measured", {}).get("tolerance") or {}
    return CloudView(
        frame="F" if inspected else "W", origin_mm=tuple(float(v) for v in origin),
        points_mm=(xyz - origin).astype(np.float32), deviation_mm=deviation, points_total=total,
        colour_scale_mm=tuple(inspection["colour_scale_mm"]) if inspected else None,
        tolerance_mm=(tolerance["lower_mm"], tolerance["upper_mm"]) if inspected and tolerance else None,
    )


def view_file(job_dir: Path) -> Path:
    """The job's encoded view, written on first use (to a temporary name, then renamed) and kept."""
    path = job_dir / VIEW_FILE
    if not path.is_file():
        try:
            report = json.loads((job_dir / "report.json").read_text(encoding="utf-8"))
        except (OSError, ValueError) as e:
            raise CloudViewError(f"{job_dir / 'report.json'}: unreadable: {e}") from e
        tmp = path.with_name(f".{VIEW_FILE}.{os.getpid()}")
        tmp.write_bytes(build_view(job_dir, report).encode())
        tmp.replace(path)
    return path
