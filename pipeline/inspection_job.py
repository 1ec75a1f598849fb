"""One call that inspects a cloud and writes everything a quality engineer opens: report.html,
report.json, figures/*.png and a PLY with the deviation field. Used by the job runner and the CLI.

Files are read in millimetres in the CAD/part frame F (PLY, PCD, XYZ clouds; STL, PLY, OBJ meshes).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
from tandemscan.config.models import InspectionConfig
from tandemscan.pipeline.export import write_ply
from tandemscan.pipeline.inspect import CadSurface, InspectionError, InspectionResult, inspect_cloud
from tandemscan.pipeline.report import build_report, write_report

DEVIATION_PLY = "cloud_deviation.ply"  # written next to report.html

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class InspectionOutputs:
    """What :func:`run_inspection` wrote, and the result behind it."""

    result: InspectionResult
    data: dict
    html: Path
    json: Path | None
    ply: Path


def _check_readable(path: Path, what: str) -> None:
    """Missing files, and PLY files without the PLY magic (whose parser would print to stderr itself)."""
    if not path.is_file():
        raise InspectionError(f"{path}: {what} file not found")
    if path.suffix.lower() == ".ply":
        with path.open("rb") as f:
            if f.read(4).rstrip(b"\r\n") != b"ply":
                raise InspectionError(f"{path}: not a PLY file (no 'ply' magic at the start)")


def load_cloud(path: Path | str) -> tuple[np.ndarray, np.ndarray | None]:
    """(points mm, normals or None) of a point-cloud file, or :class:`InspectionError` naming the file."""
    path = Path(path)
    _check_readable(path, "cloud")
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):  # we raise our own error
        cloud = o3d.io.read_point_cloud(str(path))
    if not cloud.has_points():
        raise InspectionError(f"{path}: no points could be read (formats: .ply .pcd .xyz .xyzn .pts)")
    normals = np.asarray(cloud.normals, dtype=np.float64) if cloud.has_normals() else None
    return np.asarray(cloud.points, dtype=np.float64), normals


def load_mesh(path: Path | str) -> o3d.geometry.TriangleMesh:
    """A CAD triangle mesh (mm), or :class:`InspectionError` naming the file."""
    path = Path(path)
    _check_readable(path, "CAD mesh")
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh = o3d.io.read_triangle_mesh(str(path))
    if not mesh.has_triangles():
        raise InspectionError(f"{path}: no triangles could be read (formats: .stl .ply .obj .off)")
    return mesh


def run_inspection(
    points_mm: np.ndarray,
    mesh: o3d.geometry.TriangleMesh | CadSurface,
    out_dir: Path | str,
    cfg: InspectionConfig | None = None,
    *,
    normals: np.ndarray | None = None,
    title: str = "Inspection report",
    meta: Mapping[str, str] | None = None,
    accuracy: Mapping[str, float | int | str] | None = None,
    scans_before: Sequence[np.ndarray] | None = None,
    scans_after: Sequence[np.ndarray] | None = None,
    json_name: str | None = "report.json",
) -> InspectionOutputs:
    """Inspect ``points_mm`` (frame F) against the CAD mesh and write the report and the deviation PLY
    into ``out_dir``. The PLY carries the cloud's normals when given, else the closest CAD normals.
    ``json_name=None`` leaves the JSON to the caller (it gets the same numbers as ``data``)."""
    cfg = cfg or InspectionConfig()
    surface = mesh if isinstance(mesh, CadSurface) else CadSurface(mesh)
    result = inspect_cloud(points_mm, surface, cfg)
    report = build_report(
        result, surface, cfg, title=title, meta=meta, accuracy=accuracy,
        scans_before=scans_before, scans_after=scans_after,
    )
    html, js = write_report(report, out_dir, json_name)
    ply = write_ply(
        Path(out_dir) / DEVIATION_PLY,
        result.points_mm,
        normals if normals is not None else result.cad_normals,
        {"deviation_mm": result.deviations_mm},
    )
    return InspectionOutputs(result, report.data, html, js, ply)


def inspect_files(
    cloud_path: Path | str, cad_path: Path | str, out_dir: Path | str, cfg: InspectionConfig | None = None
) -> InspectionOutputs:
    """Inspect a cloud file against a CAD mesh file; writes into ``out_dir``."""
    points, normals = load_cloud(cloud_path)
    mesh = load_mesh(cad_path)
    meta = {"cloud": str(cloud_path), "CAD mesh": str(cad_path), "points": str(len(points))}
    return run_inspection(points, mesh, out_dir, cfg, normals=normals, meta=meta)
