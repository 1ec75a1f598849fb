"""Reading point-cloud files (mm).

PLY (binary little- or big-endian and ASCII, a ``vertex`` element with x y z and optional nx ny nz; other
vertex properties and the elements after the vertices are skipped) is read here with NumPy; other formats
(PCD, XYZ, ...) and a PLY whose vertices come after another element go through Open3D, imported only then.
Writing PLY is :func:`tandemscan.pipeline.io.export.write_ply`; the job's raw scan files are
:mod:`tandemscan.pipeline.io.raw_scan`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


class CloudIOError(Exception):
    """A cloud file is missing, unreadable or empty; the message names the file."""


#: PLY scalar types -> NumPy kinds (both the PLY 1.0 names and the sized ones)
_PLY_TYPES = {"char": "i1", "uchar": "u1", "short": "i2", "ushort": "u2", "int": "i4", "uint": "u4",
              "float": "f4", "double": "f8", "int8": "i1", "uint8": "u1", "int16": "i2", "uint16": "u2",
              "int32": "i4", "uint32": "u4", "float32": "f4", "float64": "f8"}
_ENDIAN = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": "="}


class _NotHere(Exception):
    """A PLY layout this reader leaves to Open3D (vertices after another element, list properties in them)."""


def has_ply_magic(path: Path) -> bool:
    """False for a ``.ply`` file that does not start with the PLY magic (Open3D would print its own error)."""
    if path.suffix.lower() != ".ply":
        return True
    with path.open("rb") as f:
        return f.read(4).rstrip(b"\r\n") == b"ply"


def _read_ply_header(f, path: Path) -> tuple[str, int, list[tuple[str, str]]]:
    """(format, vertex count, vertex properties as (name, NumPy kind)) of the header; ``f`` is left at the
    first byte of the data."""
    fmt, count, props, element, first = None, None, [], None, True
    while (line := f.readline()) and line.strip() != b"end_header":
        words = line.decode("ascii", "replace").split()
        if words[:1] == ["format"] and len(words) > 1:
            fmt = words[1]
        elif words[:1] == ["element"] and len(words) > 2:
            element = words[1]
            if element == "vertex":
                if not first:
                    raise _NotHere
                count = int(words[2])
            first = False
        elif words[:1] == ["property"] and element == "vertex":
            if words[1] == "list" or words[1] not in _PLY_TYPES or len(words) < 3:
                raise _NotHere
            props.append((words[2], _PLY_TYPES[words[1]]))
    if not line or fmt not in _ENDIAN or count is None:
        raise CloudIOError(f"{path}: not a readable PLY header (format {fmt!r}, vertex count {count})")
    return fmt, count, props


def _vertex_columns(path: Path) -> dict[str, np.ndarray]:
    """Every vertex property of a PLY by name (binary: its own type, ASCII: float64); :class:`_NotHere` for a
    layout left to Open3D."""
    with path.open("rb") as f:
        fmt, count, props = _read_ply_header(f, path)
        names = [n for n, _ in props]
        if not {"x", "y", "z"} <= set(names):
            raise CloudIOError(f"{path}: the vertices have no x y z")
        if fmt == "ascii":
            rows = np.loadtxt(f, dtype=np.float64, max_rows=count, ndmin=2) if count else np.empty((0, len(names)))
            if rows.shape != (count, len(names)):
                raise CloudIOError(f"{path}: {len(rows)} vertex rows of {rows.shape[1]} values, "
                                   f"expected {count} of {len(names)}")
            return {n: rows[:, i] for i, n in enumerate(names)}
        dtype = np.dtype([(n, _ENDIAN[fmt] + k) for n, k in props])
        data = np.fromfile(f, dtype=dtype, count=count)
        if len(data) != count:
            raise CloudIOError(f"{path}: truncated: {len(data)} of {count} vertices")
        return {n: data[n] for n in names}


def read_ply_vertices(path: Path | str) -> dict[str, np.ndarray]:
    """Every vertex property of a PLY (``x y z`` at least, mm; others such as ``deviation_mm`` as written) by
    name, with NumPy only; raises :class:`CloudIOError` for a missing or unreadable file and for a layout only
    :func:`read_ply` reads (through Open3D)."""
    path = Path(path)
    try:
        return _vertex_columns(path)
    except OSError as e:
        raise CloudIOError(f"{path}: cannot read: {e.strerror or e}") from e
    except _NotHere as e:
        raise CloudIOError(f"{path}: vertices after another element or with list properties") from e
    except ValueError as e:
        raise CloudIOError(f"{path}: unreadable PLY data: {e}") from e


def _read_ply_numpy(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    cols = _vertex_columns(path)
    points = np.column_stack([cols[a] for a in "xyz"]).astype(np.float64)
    normals = np.column_stack([cols[a] for a in ("nx", "ny", "nz")]).astype(np.float64) \
        if {"nx", "ny", "nz"} <= set(cols) else None
    return points, normals


def _read_open3d(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    import open3d as o3d

    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):  # we raise our own error
        pcd = o3d.io.read_point_cloud(str(path))
    normals = np.asarray(pcd.normals, dtype=np.float64) if pcd.has_normals() else None
    return np.asarray(pcd.points, dtype=np.float64), normals


def read_ply(path: Path | str) -> tuple[np.ndarray, np.ndarray | None]:
    """(points (N, 3) mm, normals or None) of a PLY/PCD/XYZ cloud; raises :class:`CloudIOError`."""
    path = Path(path)
    if not path.is_file():
        raise CloudIOError(f"{path}: cloud file not found")
    if not has_ply_magic(path):
        raise CloudIOError(f"{path}: not a PLY file (no 'ply' magic at the start)")
    points, normals = None, None
    if path.suffix.lower() == ".ply":
        try:
            points, normals = _read_ply_numpy(path)
        except _NotHere:
            pass
        except ValueError as e:
            raise CloudIOError(f"{path}: unreadable PLY data: {e}") from e
    if points is None:
        points, normals = _read_open3d(path)
    if not len(points):
        raise CloudIOError(f"{path}: no points could be read (formats: .ply .pcd .xyz .xyzn .pts)")
    return points, normals
