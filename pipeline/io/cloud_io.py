"""Reading point-cloud files (mm).

Writing PLY is :func:`tandemscan.pipeline.io.export.write_ply`; the job's raw scan files are
:mod:`tandemscan.pipeline.io.raw_scan`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d


class CloudIOError(Exception):
    """A cloud file is missing, unreadable or empty; the message names the file."""


def has_ply_magic(path: Path) -> bool:
    """False for a ``.ply`` file that does not start with the PLY magic (Open3D would print its own error)."""
    if path.suffix.lower() != ".ply":
        return True
    with path.open("rb") as f:
        return f.read(4).rstrip(b"\r\n") == b"ply"


def read_ply(path: Path | str) -> tuple[np.ndarray, np.ndarray | None]:
    """(points (N, 3) mm, normals or None) of a PLY/PCD/XYZ cloud; raises :class:`CloudIOError`."""
    path = Path(path)
    if not path.is_file():
        raise CloudIOError(f"{path}: cloud file not found")
    if not has_ply_magic(path):
        raise CloudIOError(f"{path}: not a PLY file (no 'ply' magic at the start)")
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):  # we raise our own error
        pcd = o3d.io.read_point_cloud(str(path))
    if not pcd.has_points():
        raise CloudIOError(f"{path}: no points could be read (formats: .ply .pcd .xyz .xyzn .pts)")
    normals = np.asarray(pcd.normals, dtype=np.float64) if pcd.has_normals() else None
    return np.asarray(pcd.points, dtype=np.float64), normals
