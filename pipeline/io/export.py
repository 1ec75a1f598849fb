"""Export of measurement results to files other tools open: PLY with a deviation field, E57, pose log CSV.

Units: millimetres everywhere except inside E57 files, which are in metres as ASTM E2807 requires
(CloudCompare, PolyWorks and Geomagic read them as metres); the conversion happens here only.
Poses: ``T_W_S`` maps scanner-frame points (S) into the world/part frame of the merged cloud (mm).
"""

from __future__ import annotations

import csv
import logging
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tandemscan.pipeline.geometry.frames import to_quaternion, to_rpy, transform_points

log = logging.getLogger(__name__)

MM_PER_M = 1000.0
#: a PLY's records are formed and written this many points at a time (about 40 MB)
PLY_CHUNK_POINTS = 1_000_000


class ExportError(ValueError):
    """Data that cannot be written as asked: mismatched lengths, no scans, bad shapes."""


@dataclass(frozen=True)
class PosedScan:
    """One scan in its own scanner frame S (mm) with its pose ``T_W_S`` and free-form log fields;
    ``point_count`` is the scan's size where ``points_S_mm`` is a thinned copy of it (None: all of it)."""

    name: str
    T_W_S: np.ndarray
    points_S_mm: np.ndarray
    meta: Mapping[str, float | int | str] = field(default_factory=dict)
    point_count: int | None = None

    @property
    def size(self) -> int:
        """Points the scan measured."""
        return len(self.points_S_mm) if self.point_count is None else int(self.point_count)

    def points_W_mm(self) -> np.ndarray:
        """The scan's points in the world/part frame, mm."""
        return transform_points(self.T_W_S, self.points_S_mm)


def _columns(n: int, arr: np.ndarray | None, what: str, width: int) -> np.ndarray | None:
    if arr is None:
        return None
    a = np.asarray(arr, dtype=np.float64)
    if a.shape != ((n, width) if width > 1 else (n,)):
        raise ExportError(f"{what}: expected {n} rows of {width}, got shape {a.shape}")
    return a


def write_ply(
    path: Path | str,
    points_mm: np.ndarray,
    normals: np.ndarray | None = None,
    scalars: Mapping[str, np.ndarray] | None = None,
) -> Path:
    """Write a binary little-endian PLY: x y z (float64, mm), optional nx ny nz, one float32 property per
    scalar field (e.g. ``deviation_mm``; CloudCompare shows each as a scalar field). Returns the path."""
    pts = np.asarray(points_mm, dtype=np.float64)  # its shape checked by PlyChunk.fields
    return write_ply_streamed(path, len(pts), [PlyChunk(pts, normals, scalars or {})])


@dataclass(frozen=True)
class PlyChunk:
    """Consecutive vertices of a PLY: points (N, 3) mm, unit normals (N, 3) or None, float32 scalar fields."""

    points_mm: np.ndarray
    normals: np.ndarray | None = None
    scalars: Mapping[str, np.ndarray] = field(default_factory=dict)

    def fields(self) -> list[tuple[str, str, np.ndarray]]:
        """(PLY property, numpy kind, values) of each column, validated."""
        pts = np.asarray(self.points_mm, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ExportError(f"points: expected (N, 3), got shape {pts.shape}")
        n = len(pts)
        fields: list[tuple[str, str, np.ndarray]] = [(a, "f8", pts[:, i]) for i, a in enumerate("xyz")]
        nrm = _columns(n, self.normals, "normals", 3)
        if nrm is not None:
            fields += [(a, "f4", nrm[:, i]) for i, a in enumerate(("nx", "ny", "nz"))]
        for name, values in self.scalars.items():
            if not name.isidentifier():
                raise ExportError(f"scalar field name {name!r} is not a plain identifier")
            fields.append((name, "f4", _columns(n, values, name, 1)))
        return fields


def write_ply_streamed(path: Path | str, count: int, chunks: Iterable[PlyChunk]) -> Path:
    """Write a PLY as :func:`write_ply` does from ``chunks`` taken one at a time (a cloud tile by tile:
    ``tiles.write_cloud_ply``), ``count`` vertices in all, known before the first (the tiles' voxel counts): the same
    bytes as :func:`write_ply` of the chunks one after the other. Every chunk has the first one's fields; a total
    other than ``count`` raises :class:`ExportError` and leaves no file. Returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    written, names = 0, None
    try:
        with path.open("wb") as f:
            for chunk in chunks:
                fields = chunk.fields()
                if names is None:
                    names = [(name, kind) for name, kind, _ in fields]
                    f.write(_ply_header_bytes(count, names))
                elif [(name, kind) for name, kind, _ in fields] != names:
                    raise ExportError(f"PLY chunk fields {[n for n, _, _ in fields]} differ from {names}")
                written += _write_records(f, fields)
            if names is None:
                names = [(a, "f8") for a in "xyz"]
                f.write(_ply_header_bytes(count, names))
        if written != count:
            raise ExportError(f"PLY {path.name}: {written} vertices written, the header says {count}")
    except BaseException:
        path.unlink(missing_ok=True)
        raise
    log.info("wrote %s (%d points, fields %s)", path, count, [name for name, _ in names])
    return path


def _ply_header_bytes(count: int, fields: Sequence[tuple[str, str]]) -> bytes:
    ply_type = {"f8": "double", "f4": "float"}
    header = ["ply", "format binary_little_endian 1.0", "comment units mm", f"element vertex {count}"]
    header += [f"property {ply_type[kind]} {name}" for name, kind in fields]
    header.append("end_header\n")
    return "\n".join(header).encode("ascii")


def _write_records(f, fields: Sequence[tuple[str, str, np.ndarray]]) -> int:
    """The columns ``fields`` as little-endian records, a chunk of :data:`PLY_CHUNK_POINTS` at a time (no copy
    of a whole cloud); returns the records written."""
    n = len(fields[0][2])
    record = np.dtype([(name, "<" + kind) for name, kind, _ in fields])
    data = np.empty(min(n, PLY_CHUNK_POINTS), dtype=record)
    for lo in range(0, n, PLY_CHUNK_POINTS):
        rows = data[: min(PLY_CHUNK_POINTS, n - lo)]
        for name, _, values in fields:
            rows[name] = values[lo:lo + len(rows)]
        rows.tofile(f)
    return n


def _e57_pose(T_W_S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rotation quaternion w, x, y, z; translation m) of a pose in mm, as E57 stores it."""
    t_mm, q_xyzw = to_quaternion(T_W_S)
    return np.array([q_xyzw[3], *q_xyzw[:3]]), np.asarray(t_mm) / MM_PER_M


def _e57_xyz(points_mm: np.ndarray) -> dict[str, np.ndarray]:
    """pye57's columns (float64, m) of ``points_mm`` (N, 3), any float dtype: made one column at a time, so a
    merged cloud of 18 M float32 points takes its 0.4 GB of columns and no whole-cloud temporaries."""
    return {name: np.divide(points_mm[:, axis], MM_PER_M, dtype=np.float64)
            for axis, name in enumerate(("cartesianX", "cartesianY", "cartesianZ"))}


def write_e57(
    path: Path | str,
    scans: Iterable[PosedScan],
    merged_points_mm: np.ndarray | None = None,
    merged_name: str = "merged",
) -> Path:
    """Write an E57 file: one data3D scan per pose (points in its scanner frame, pose = ``T_W_S``), then,
    when given, the merged cloud in the world frame with an identity pose. Metres inside the file (single
    precision, as pye57 writes it). ``scans`` is consumed once, in order, and each scan written before the
    next is taken: a generator reading them from their files holds one scan in memory at a time."""
    import pye57  # local: only the export needs it

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    e57 = pye57.E57(str(path), mode="w")
    written = 0
    try:
        for scan in scans:
            pts = np.asarray(scan.points_S_mm)  # float32 as stored: converted a column at a time
            if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
                raise ExportError(f"E57 scan {scan.name!r}: expected (N>0, 3) points, got shape {pts.shape}")
            rotation, translation = _e57_pose(scan.T_W_S)
            e57.write_scan_raw(_e57_xyz(pts), name=scan.name, rotation=rotation, translation=translation)
            written += 1
            del pts, scan
        if not written and merged_points_mm is None:
            raise ExportError("E57: nothing to write (no scans and no merged cloud)")
        if merged_points_mm is not None:
            merged = np.asarray(merged_points_mm)  # as it is: its columns are converted one at a time
            if merged.ndim != 2 or merged.shape[1] != 3 or len(merged) == 0:
                raise ExportError(f"E57 merged cloud: expected (N>0, 3) points, got shape {merged.shape}")
            e57.write_scan_raw(
                _e57_xyz(merged), name=merged_name, rotation=np.array([1.0, 0, 0, 0]), translation=np.zeros(3)
            )
    except BaseException:
        e57.close()
        path.unlink(missing_ok=True)  # no half-written E57 left behind
        raise
    e57.close()
    log.info("wrote %s (%d scans%s)", path, written, " + merged" if merged_points_mm is not None else "")
    return path


def write_pose_log(path: Path | str, scans: Sequence[PosedScan]) -> Path:
    """Write the job's pose log as CSV: one row per scan with ``T_W_S`` as position (mm), quaternion
    (x, y, z, w), roll-pitch-yaw (deg, fixed axes x-y-z), the point count, then every ``meta`` key."""
    extra: list[str] = []
    for scan in scans:
        extra += [k for k in scan.meta if k not in extra]
    head = ["index", "name", "points", "x_mm", "y_mm", "z_mm", "qx", "qy", "qz", "qw"]
    head += ["roll_deg", "pitch_deg", "yaw_deg", *extra]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(head)
        for i, scan in enumerate(scans):
            t_mm, q = to_quaternion(scan.T_W_S)
            _, rpy = to_rpy(scan.T_W_S)
            row = [i, scan.name, scan.size, *(f"{v:.6f}" for v in t_mm), *(f"{v:.9f}" for v in q)]
            row += [f"{v:.6f}" for v in np.degrees(rpy)]
            w.writerow(row + [scan.meta.get(k, "") for k in extra])
    return path
