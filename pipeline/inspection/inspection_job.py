"""One call that inspects a cloud and writes everything a quality engineer opens: report.html,
report.json, figures/*.png and a PLY with the deviation field. Used by the job runner and the CLI.

:func:`run_inspection` takes a cloud in the CAD/part frame F; :func:`align_and_inspect` one in a frame W of
its own (the job's world), registered to F first (:mod:`tandemscan.pipeline.inspection.alignment`). Files are read in
millimetres (PLY, PCD, XYZ clouds; STL, PLY, OBJ meshes).
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import logging
from collections.abc import Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree
from tandemscan.config.inspection_template import InspectionTemplate
from tandemscan.config.models import InspectionConfig
from tandemscan.pipeline.geometry.frames import rotate_vectors, transform_points
from tandemscan.pipeline.geometry.part import PartMeshError, read_mesh_file
from tandemscan.pipeline.inspection.alignment import Alignment, AlignmentCriteria, AlignmentFailed, align
from tandemscan.pipeline.inspection.cad_orientation import orient
from tandemscan.pipeline.inspection.characteristics import CharacteristicResult, MeasuredCloud, evaluate
from tandemscan.pipeline.inspection.datum_frame import DatumPatch, align_datums
from tandemscan.pipeline.inspection.decision import DecisionRule
from tandemscan.pipeline.inspection.inspect import (
    CadSurface,
    InspectionError,
    InspectionResult,
    as_points,
    in_chunks,
    inspect_cloud,
)
from tandemscan.pipeline.inspection.point_uncertainty import GivenUncertainty, UncertaintyModel, alignment_covariance
from tandemscan.pipeline.inspection.qif import RESULTS_FILE, MeasuredPart, write_results
from tandemscan.pipeline.inspection.report import build_report, failed_report, in_background, write_report
from tandemscan.pipeline.inspection.stitch_quality import overlap_quality
from tandemscan.pipeline.inspection.verdict import VerdictContext, judge
from tandemscan.pipeline.io.cloud_io import CloudIOError, read_ply, read_ply_vertices
from tandemscan.pipeline.io.export import write_ply
from tandemscan.pipeline.planning.coverage import CoverageFigures

DEVIATION_PLY = "cloud_deviation.ply"  # written next to report.html

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class InspectionOutputs:
    """What :func:`run_inspection` wrote, and the result behind it. A part whose alignment to CAD failed has
    no ``result`` nor ``ply``: its report says why, with the verdict "indeterminate" (``data["reason"]``)."""

    result: InspectionResult | None
    data: dict
    html: Path
    json: Path | None
    ply: Path | None
    characteristics: tuple[CharacteristicResult, ...] = ()
    qif: Path | None = None  # results.qif, written with a template


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
    alignment: Alignment | None = None,
    overlap: Future | None = None,
    template: InspectionTemplate | None = None,
    part: Mapping[str, str] | None = None,
    history: Mapping[str, Sequence[Mapping]] | None = None,
    uncertainty: UncertaintyModel | None = None,
    context: VerdictContext | None = None,
    coverage: CoverageFigures | None = None,
) -> InspectionOutputs:
    """Inspect ``points_mm`` (frame F) against the CAD mesh and write the report and the deviation PLY
    into ``out_dir``. The PLY carries the cloud's normals when given, else the closest CAD normals.
    ``json_name=None`` leaves the JSON to the caller (it gets the same numbers as ``data``);
    ``alignment`` says how the points were placed in F (None: they came in F); ``overlap``: the scans'
    :func:`overlap_quality`, being computed (else it is started here, while the cloud is inspected);
    ``template``: the part's characteristics (those without limits of their own under ``cfg``'s tolerance, the
    general one), evaluated and reported first and written as ``results.qif``;
    ``part``: its part number, serial, template file and measuring system, as the report and the QIF name them;
    ``history``: the part's earlier serials' results per characteristic (``report.build_report``);
    ``uncertainty``: what knows the points' uncertainty (None: the cloud states none, U = 0) and ``context``
    the installation and verification the verdict is made in (``verdict.judge``); ``coverage``: the job's
    plan's (``report.build_report``).

    Nineteen parameters: the cloud, the mesh, where to write and the settings, then keyword-only inputs of the
    report, each optional (a caller passes those it has)."""
    cfg = cfg or InspectionConfig()
    if template is not None:
        template = template.with_general_tolerance(cfg.tolerance_lower_mm, cfg.tolerance_upper_mm)
    surface = mesh if isinstance(mesh, CadSurface) else CadSurface(mesh)
    if overlap is None and scans_before is not None:
        overlap = in_background(overlap_quality, scans_before, scans_after)
    result = inspect_cloud(points_mm, surface, cfg)
    placed = alignment or Alignment("none", np.eye(4), 0.0, "the cloud as given")
    u = (uncertainty or GivenUncertainty(0.0)).evaluate(
        result.points_mm, result.cad_normals, cfg.decision_k, placed.T_F_W, placed.method,
        None if placed.excluded is None else ~placed.excluded, alignment_covariance(placed))
    if uncertainty is None:
        u = dataclasses.replace(u, notes=u.notes | {"cloud": "the cloud states no uncertainty: U = 0"})
    result = judge(result, u, cfg, context or VerdictContext())
    with ThreadPoolExecutor(2, thread_name_prefix="inspection-outputs") as pool:  # beside the figures: the
        measured = None if template is None else pool.submit(  # characteristics and the file
            evaluate, template, measured_cloud(result, surface, u.expanded_mm), DecisionRule.of(cfg))
        ply = pool.submit(
            write_ply,
            Path(out_dir) / DEVIATION_PLY,
            result.points_mm,
            normals if normals is not None else result.cad_normals,
            {"deviation_mm": result.deviations_mm, "uncertainty_mm": u.expanded_mm},
        )
        report = build_report(
            result, surface, cfg, title=title, meta=meta, accuracy=accuracy,
            scans_before=scans_before, scans_after=scans_after, alignment=alignment, overlap=overlap,
            characteristics=() if measured is None else measured, part=part, history=history, coverage=coverage,
        )
        html, js = write_report(report, out_dir, json_name)
    characteristics = () if measured is None else measured.result()
    qif = None if template is None else write_results(
        Path(out_dir) / RESULTS_FILE, measured_part(template, part or {}), characteristics, result.points_mm)
    return InspectionOutputs(result, report.data, html, js, ply.result(), characteristics, qif)


def measured_part(template: InspectionTemplate, part: Mapping[str, str]) -> MeasuredPart:
    """What results.qif names: ``part``'s part number (else the template's), serial and measuring system, the
    template's description of the part, measured now."""
    return MeasuredPart(part.get("part_number", template.part_number), template.part, part.get("serial"),
                        part.get("measuring_system", "tandemscan"), dt.datetime.now(dt.UTC))


def measured_cloud(result: InspectionResult, surface: CadSurface, expanded_mm: np.ndarray) -> MeasuredCloud:
    """What the characteristics are evaluated on: the inspection's points, deviations, closest triangles and
    per-point expanded uncertainty (``expanded_mm``, ``point_uncertainty``)."""
    assert result.triangle_ids is not None  # inspect_cloud keeps them
    return MeasuredCloud(result.points_mm, result.deviations_mm, result.triangle_ids, expanded_mm, surface)


def align_and_inspect(
    points_W_mm: np.ndarray,
    mesh: o3d.geometry.TriangleMesh | CadSurface,
    out_dir: Path | str,
    cfg: InspectionConfig | None = None,
    *,
    normals_W: np.ndarray | None = None,
    start_T_F_W: np.ndarray | None = None,
    start: str = "as given",
    prior_T_F_W: np.ndarray | None = None,
    viewpoints_W: np.ndarray | None = None,
    scans_before_W: Sequence[np.ndarray] | None = None,
    scans_after_W: Sequence[np.ndarray] | None = None,
    **report: Any,
) -> InspectionOutputs:
    """Register a cloud measured in frame W to the CAD frame F by ``cfg.alignment`` from ``start_T_F_W``
    (where the job's anchor put it, or the cloud as given; described by ``start``; ``prior_T_F_W``: the
    placement that holds what the surface does not fix, None where the start is unknown), orient the CAD by
    the measured side (:func:`measured_side`: ``viewpoints_W``, the scanner positions (K, 3) mm, else the
    cloud's ``normals_W``), then inspect and write as :func:`run_inspection` (``report`` passes its title,
    meta, accuracy and json_name). The points on reference spheres are left out of the inspection; the
    stitching views are mapped into F as well. A ``template`` among ``report`` sets the alignment
    (:meth:`InspectionTemplate.inspection_config`). A failed alignment writes the report of a failed
    inspection (verdict "indeterminate", the reason) and returns it without a result.

    Twelve parameters: the cloud, the mesh, where to write and the settings, then keyword-only inputs of the
    alignment and the stitching views, each optional."""
    cfg = cfg or InspectionConfig()
    if report.get("template") is not None:
        cfg = report["template"].inspection_config(cfg)
    surface = mesh if isinstance(mesh, CadSurface) else CadSurface(mesh)
    p = as_points(points_W_mm)
    overlap = None  # a rigid motion changes no overlap: computed in W while the cloud is aligned and inspected
    if scans_before_W is not None:
        overlap = in_background(overlap_quality, scans_before_W, scans_after_W)
    try:
        alignment = align(surface, p, AlignmentCriteria.from_section(cfg), start_T_F_W, start, prior_T_F_W)
    except AlignmentFailed as e:  # a failed inspection, with the reason on its report
        log.warning("%s", e)
        failed = failed_report(str(e), e.attempt, title=report.get("title", "Inspection report"),
                               meta=report.get("meta"))
        html, js = write_report(failed, out_dir, report.get("json_name", "report.json"))
        return InspectionOutputs(None, failed.data, html, js, None)
    template = report.get("template")
    if template is not None and template.alignment.method == "datums":
        alignment = align_datums(surface, p, alignment, [
            DatumPatch(d.feature, d.patch, template.patches[d.patch].min_mm, template.patches[d.patch].max_mm)
            for d in template.alignment.datums])
    keep = np.ones(len(p), bool) if alignment.excluded is None else ~alignment.excluded
    T = alignment.T_F_W
    log.info("aligned to CAD by %s: residual %.4f mm, %d points on reference spheres left out",
             alignment.method, alignment.residual_mm, int((~keep).sum()))
    surface, note = measured_side(surface, p, T, normals_W, viewpoints_W)
    if note:
        report["meta"] = dict(report.get("meta") or {}) | {"CAD winding": note}

    def into_F(scans: Sequence[np.ndarray] | None) -> PlacedScans | None:
        return None if scans is None else PlacedScans(scans, T)

    every = bool(keep.all())  # no copy of the cloud where no point is left out
    return run_inspection(
        in_chunks(transform_points, T, p if every else p[keep]), surface, out_dir, cfg,
        normals=None if normals_W is None else in_chunks(
            rotate_vectors, T, normals_W if every else np.asarray(normals_W)[keep]),
        scans_before=into_F(scans_before_W), scans_after=into_F(scans_after_W), alignment=alignment,
        overlap=overlap, **report,
    )


ORIENTATION_POINTS = 50_000  # measured points that vote for the side each patch of the CAD faces


def measured_side(surface: CadSurface, points_W_mm: np.ndarray, T_F_W: np.ndarray, normals_W: np.ndarray | None,
                  viewpoints_W: np.ndarray | None) -> tuple[CadSurface, str]:
    """The CAD surface wound so that its normals point to the measured side (:func:`cad_orientation.orient`),
    and the warning where the file's winding disagreed (else ""). The side is where the points were seen
    from: the nearest of ``viewpoints_W`` (scanner positions, W, mm) to each point, else the cloud's unit
    normals (toward the scanner, as a scanner writes them); with neither, closed patches alone are decided."""
    step = max(1, len(points_W_mm) // ORIENTATION_POINTS)
    p_W = np.asarray(points_W_mm)[::step]
    if viewpoints_W is not None and len(viewpoints_W):
        eye = np.asarray(viewpoints_W, float)[cKDTree(viewpoints_W).query(p_W)[1]]
        toward, by = rotate_vectors(T_F_W, eye - p_W), "scanner positions"
    elif normals_W is not None:
        toward, by = rotate_vectors(T_F_W, np.asarray(normals_W, float)[::step]), "cloud normals"
    else:
        toward, by = None, "no scanner positions, no cloud normals"
    ids = surface.closest(transform_points(T_F_W, p_W)).triangle_ids
    o = orient(np.asarray(surface.mesh.vertices), np.asarray(surface.mesh.triangles), ids, toward, by)
    return surface.oriented(o.reversed), o.note


class PlacedScans(Sequence):
    """Scans' points (mm) placed by a pose each, or all by one: scan ``k`` is ``poses[k]`` (or ``poses``, one
    4x4) applied to ``scans[k]``, mapped each time it is asked for, never held. The stitching figure draws two of
    the hundreds of scans a job has, and its overlap figures read each scan about twice: a whole part's scans
    placed twice (before and after the correction) and moved into F would hold three copies of them."""

    def __init__(self, scans: Sequence[np.ndarray], poses: np.ndarray | Sequence[np.ndarray]):
        self._scans = scans
        one = isinstance(poses, np.ndarray) and poses.shape == (4, 4)
        self._poses = [np.asarray(poses, float)] * len(scans) if one else [np.asarray(T, float) for T in poses]
        if len(self._poses) != len(scans):
            raise ValueError(f"{len(scans)} scans but {len(self._poses)} poses")

    def __len__(self) -> int:
        return len(self._scans)

    def __getitem__(self, i):  # type: ignore[override]
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(len(self)))]
        return transform_points(self._poses[i], self._scans[i])


def inspect_files(
    cloud_path: Path | str, cad_path: Path | str, out_dir: Path | str, cfg: InspectionConfig | None = None,
    template: InspectionTemplate | None = None, part: Mapping[str, str] | None = None,
    point_uncertainty_mm: float | None = None,
) -> InspectionOutputs:
    """Inspect a cloud file against a CAD mesh file; writes into ``out_dir``. The cloud is registered by
    ``cfg.alignment`` (the template's, when given) from where it lies (within the first trim distance of its
    place on CAD); ``template`` and ``part`` as :func:`run_inspection` takes them. The points' expanded
    uncertainty (k = ``cfg.decision_k``, mm) is ``point_uncertainty_mm``, else the PLY's ``uncertainty_mm``
    property where it has one (a job's ``cloud_deviation.ply``), else none is known (0)."""
    try:
        points, normals = read_ply(cloud_path)
        mesh = read_mesh_file(Path(cad_path), what="CAD mesh")
    except (CloudIOError, PartMeshError) as e:
        raise InspectionError(str(e)) from e
    own = point_uncertainty_mm
    if own is None and Path(cloud_path).suffix.lower() == ".ply":
        try:
            own = read_ply_vertices(cloud_path).get("uncertainty_mm")
        except CloudIOError:  # a layout only Open3D reads: it has no such property for us
            own = None
    cfg = cfg or InspectionConfig()
    meta = {"cloud": str(cloud_path), "CAD mesh": str(cad_path), "points": str(len(points))}
    given = None if own is None else GivenUncertainty(np.asarray(own, float), cfg.decision_k)
    return align_and_inspect(points, mesh, out_dir, cfg, normals_W=normals, start="the cloud as given", meta=meta,
                             template=template, part=part, uncertainty=given)
