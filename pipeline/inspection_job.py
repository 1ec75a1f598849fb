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
from tandemscan.pipeline.cloud_io import CloudIOError, read_ply
from tandemscan.pipeline.export import write_ply
from tandemscan.pipeline.inspect import CadSurface, InspectionError, InspectionResult, inspect_cloud
from tandemscan.pipeline.part import PartMeshError, read_mesh_file
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
    try:
        points, normals = read_ply(cloud_path)
        mesh = read_mesh_file(Path(cad_path), what="CAD mesh")
    except (CloudIOError, PartMeshError) as e:
        raise InspectionError(str(e)) from e
    meta = {"cloud": str(cloud_path), "CAD mesh": str(cad_path), "points": str(len(points))}
    return run_inspection(points, mesh, out_dir, cfg, normals=normals, meta=meta)
