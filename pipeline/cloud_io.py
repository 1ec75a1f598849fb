"""Point-cloud files: PLY read and write (binary), mm, with optional normals."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d


class CloudIOError(Exception):
    """A cloud file is missing, unreadable or empty."""


def write_ply(path: Path, points_mm: np.ndarray, normals: np.ndarray | None = None) -> None:
    """Write a binary PLY (mm)."""
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points_mm, np.float64)))
    if normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(np.asarray(normals, np.float64))
    if not o3d.io.write_point_cloud(str(path), pcd, write_ascii=False):
        raise CloudIOError(f"{path}: could not write the cloud")


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """(points (N, 3) mm, normals or None) of a PLY/PCD/XYZ cloud."""
    path = Path(path)
    if not path.is_file():
        raise CloudIOError(f"{path}: cloud file not found")
    pcd = o3d.io.read_point_cloud(str(path))
    if len(pcd.points) == 0:
        raise CloudIOError(f"{path}: no points could be read")
    normals = np.asarray(pcd.normals) if pcd.has_normals() else None
    return np.asarray(pcd.points), normals
