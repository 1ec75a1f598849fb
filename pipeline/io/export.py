"""Export of measurement results to files other tools open: PLY with a deviation field, E57, pose log CSV.

Units: millimetres everywhere except inside E57 files, which are in metres as ASTM E2807 requires
(CloudCompare, PolyWorks and Geomagic read them as metres); the conversion happens here only.
Poses: ``T_W_S`` maps scanner-frame points (S) into the world/part frame of the merged cloud (mm).
"""

from __future__ import annotations

import csv
import logging
import uuid
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np
from tandemscan.pipeline.geometry.frames import to_quaternion, to_rpy, transform_points
from tandemscan.pipeline.geometry.units import box_mm
from tandemscan.pipeline.io.raw_scan import read_raw_scan

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
                del chunk, fields  # not held while the next chunk is read
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
    """pye57's columns (float64, m) of ``points_mm`` (N, 3), any float dtype: made one column at a time."""
    return {name: np.divide(points_mm[:, axis], MM_PER_M, dtype=np.float64)
            for axis, name in enumerate(E57_XYZ)}


E57_XYZ = ("cartesianX", "cartesianY", "cartesianZ")
#: points a block of the E57 writer's buffers (three float64 columns: 24 MB)
E57_BLOCK_POINTS = 1_000_000


class PointBlocks(Protocol):
    """A cloud given a block at a time (a tile at a time: ``tiles.TiledCloud``), mm: its point count, its bounds
    (per axis, mm) and its blocks, (N, 3) each, in order; :meth:`blocks` may be asked more than once."""

    @property
    def count(self) -> int: ...

    def bounds_mm(self) -> tuple[np.ndarray, np.ndarray]: ...

    def blocks(self) -> Iterator[np.ndarray]: ...


@dataclass(frozen=True)
class ArrayBlocks:
    """A cloud in memory, (N, 3) mm, as :class:`PointBlocks` of :data:`E57_BLOCK_POINTS` rows (views, no copy)."""

    points_mm: np.ndarray

    @property
    def count(self) -> int:
        return len(self.points_mm)

    def bounds_mm(self) -> tuple[np.ndarray, np.ndarray]:
        return box_mm(self.points_mm)

    def blocks(self) -> Iterator[np.ndarray]:
        for lo in range(0, len(self.points_mm), E57_BLOCK_POINTS):
            yield self.points_mm[lo:lo + E57_BLOCK_POINTS]


def _write_e57_blocks(e57, cloud: PointBlocks, name: str, rotation: np.ndarray, translation: np.ndarray) -> None:
    """One data3D scan of ``cloud`` (points x y z only, metres, single precision) written a block at a time: the
    nodes and values ``pye57.E57.write_scan_raw`` writes for the whole cloud at once (its bounds, from
    ``cloud.bounds_mm`` divided as each point is, and its pose), with buffers of :data:`E57_BLOCK_POINTS` points
    instead of a copy of every column."""
    from pye57 import libe57  # local: only the export needs it

    imf = e57.image_file
    n = cloud.count
    lo_mm, hi_mm = cloud.bounds_mm()
    bb_min, bb_max = lo_mm / MM_PER_M, hi_mm / MM_PER_M  # min(p / 1000) = min(p) / 1000: division is monotone
    scan = _e57_scan_node(e57, name, n, (bb_min, bb_max), rotation, translation)
    prototype = libe57.StructureNode(imf)
    centre = (bb_max + bb_min) / 2
    for axis, column in enumerate(E57_XYZ):
        prototype.set(column, libe57.FloatNode(imf, centre[axis], libe57.E57_SINGLE, bb_min[axis], bb_max[axis]))
    arrays, buffers = e57.make_buffers(list(E57_XYZ), min(max(n, 1), E57_BLOCK_POINTS))
    points = libe57.CompressedVectorNode(imf, prototype, libe57.VectorNode(imf, True))
    scan.set("points", points)
    e57.data3d.append(scan)
    writer = points.writer(buffers)
    written = 0
    for block in cloud.blocks():
        for at in range(0, len(block), E57_BLOCK_POINTS):
            rows = block[at:at + E57_BLOCK_POINTS]
            for axis, column in enumerate(E57_XYZ):
                np.divide(rows[:, axis], MM_PER_M, out=arrays[column][:len(rows)], dtype=np.float64)
            writer.write(len(rows))
            written += len(rows)
    writer.close()
    if written != n:
        raise ExportError(f"E57 scan {name!r}: {written} points written, {n} announced")


def _e57_scan_node(e57, name: str, n: int, bounds_m: tuple[np.ndarray, np.ndarray], rotation: np.ndarray,
                   translation: np.ndarray):
    """A data3D scan's header node as ``pye57.E57.write_scan_raw`` makes it for ``n`` points with bounds
    ``bounds_m`` (its scanner frame, m) and its pose (quaternion w x y z, translation m): name, index and cartesian
    bounds (the latter placed by the pose), pose, zero atmosphere and acquisition times."""
    from pye57 import libe57  # local: only the export needs it

    imf = e57.image_file
    scan = libe57.StructureNode(imf)
    scan.set("guid", libe57.StringNode(imf, f"{{{uuid.uuid4()}}}"))
    scan.set("name", libe57.StringNode(imf, name))
    for key in ("temperature", "relativeHumidity", "atmosphericPressure"):
        scan.set(key, libe57.FloatNode(imf, 0))
    scan.set("description", libe57.StringNode(imf, f"pye57 v{_pye57_version()}"))
    index = libe57.StructureNode(imf)
    for key, value in (("rowMinimum", 0), ("rowMaximum", n - 1), ("columnMinimum", 0), ("columnMaximum", 0),
                       ("returnMinimum", 0), ("returnMaximum", 0)):
        index.set(key, libe57.IntegerNode(imf, value))
    scan.set("indexBounds", index)
    bounds = libe57.StructureNode(imf)
    lo_g, hi_g = (e57.to_global(b.reshape(-1, 3), rotation, translation)[0] for b in bounds_m)
    for axis, a in enumerate("xyz"):
        bounds.set(f"{a}Minimum", libe57.FloatNode(imf, lo_g[axis]))
        bounds.set(f"{a}Maximum", libe57.FloatNode(imf, hi_g[axis]))
    scan.set("cartesianBounds", bounds)
    pose = libe57.StructureNode(imf)
    scan.set("pose", pose)
    for part, values, axes in (("rotation", rotation, "wxyz"), ("translation", translation, "xyz")):
        node = libe57.StructureNode(imf)
        for i, a in enumerate(axes):
            node.set(a, libe57.FloatNode(imf, values[i]))
        pose.set(part, node)
    for key in ("acquisitionStart", "acquisitionEnd"):
        when = libe57.StructureNode(imf)
        scan.set(key, when)
        when.set("dateTimeValue", libe57.FloatNode(imf, 0))
        when.set("isAtomicClockReferenced", libe57.IntegerNode(imf, False))
    return scan


def _pye57_version() -> str:
    from pye57.__version__ import __version__

    return __version__


def write_e57(
    path: Path | str,
    scans: Iterable[PosedScan],
    merged_points_mm: np.ndarray | PointBlocks | None = None,
    merged_name: str = "merged",
) -> Path:
    """Write an E57 file: one data3D scan per pose (points in its scanner frame, pose = ``T_W_S``), then,
    when given, the merged cloud in the world frame with an identity pose (an array, or :class:`PointBlocks`
    written a block at a time: a cloud tile by tile). Metres inside the file (single precision, as pye57 writes
    it). ``scans`` is consumed once, in order, and each scan written before the next is taken: a generator
    reading them from their files holds one scan in memory at a time."""
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
            merged = (ArrayBlocks(np.asarray(merged_points_mm)) if isinstance(merged_points_mm, np.ndarray)
                      else merged_points_mm)
            if isinstance(merged, ArrayBlocks) and (merged.points_mm.ndim != 2 or merged.points_mm.shape[1] != 3):
                raise ExportError(f"E57 merged cloud: expected (N>0, 3) points, got shape {merged.points_mm.shape}")
            if merged.count == 0:
                raise ExportError("E57 merged cloud: expected (N>0, 3) points, got none")
            _write_e57_blocks(e57, merged, merged_name, np.array([1.0, 0, 0, 0]), np.zeros(3))
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


@dataclass(frozen=True)
class ScanExports:
    """What a job's pose log and E57 are written from (:func:`write_scan_exports`, in a process of its own): the
    scans' poses ``T_W_S``, log fields and point counts (``scans``: :class:`PosedScan` whose points are not needed,
    ``point_count`` set), each one's raw scan file (``files``, read one at a time for the E57; a scan that saw nothing
    is left out of it), the merged cloud (W, mm, :class:`PointBlocks`; None: empty) and the two files' paths.
    Small to pickle: the cloud is a shared-memory array or tiles' files (docs/end-of-job.md)."""

    pose_log: Path
    e57: Path
    scans: tuple[PosedScan, ...]
    files: tuple[Path, ...]
    merged: PointBlocks | None


def write_scan_exports(exports: ScanExports) -> None:
    """``exports.pose_log`` (every scan) and, where some scan measured points, ``exports.e57`` (the scans read from
    their files one at a time, then the merged cloud), frame W, mm."""
    write_pose_log(exports.pose_log, exports.scans)
    if any(s.size for s in exports.scans):
        write_e57(exports.e57, _full_scans(exports.scans, exports.files), exports.merged)


def _full_scans(scans: Sequence[PosedScan], files: Sequence[Path]) -> Iterator[PosedScan]:
    """``scans`` with all their points (S, mm, float32 as stored), each read from its file of ``files`` when the E57
    writer asks for it: one full scan in memory at a time. Scans that saw nothing are left out (E57 has no empty
    scans)."""
    empty = 0
    for scan, file in zip(scans, files, strict=True):
        points, _ = read_raw_scan(file, np.float32)
        if len(points):
            yield PosedScan(scan.name, scan.T_W_S, points, scan.meta)
        else:
            empty += 1
        del points
    if empty:
        log.warning("%d scans saw nothing and are left out of the E57", empty)
