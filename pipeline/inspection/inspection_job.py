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
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Self

import numpy as np
from scipy.spatial import cKDTree
from tandemscan.config.inspection_template import InspectionTemplate
from tandemscan.config.models import InspectionConfig
from tandemscan.pipeline.geometry.frames import rotate_vectors, transform_points
from tandemscan.pipeline.geometry.part import PartMeshError, read_mesh_file
from tandemscan.pipeline.geometry.units import MM_PER_UNIT, extent_mm, scale_mismatch
from tandemscan.pipeline.inspection.alignment import (
    Alignment,
    AlignmentCriteria,
    AlignmentFailed,
    align,
    sphere_balls,
)
from tandemscan.pipeline.inspection.cad_orientation import orient
from tandemscan.pipeline.inspection.characteristic_figures import Surroundings
from tandemscan.pipeline.inspection.characteristics import CharacteristicResult, MeasuredCloud, evaluate
from tandemscan.pipeline.inspection.datum_frame import DatumPatch, align_datums
from tandemscan.pipeline.inspection.decision import DecisionRule
from tandemscan.pipeline.inspection.deviation_areas import DeviationArea
from tandemscan.pipeline.inspection.inspect import (
    CadSurface,
    InspectionCriteria,
    InspectionError,
    InspectionResult,
    as_points,
    in_chunks,
    inspect_cloud,
)
from tandemscan.pipeline.inspection.point_uncertainty import GivenUncertainty, UncertaintyModel, alignment_covariance
from tandemscan.pipeline.inspection.qif import RESULTS_FILE, MeasuredPart, write_results
from tandemscan.pipeline.inspection.region_points import (
    REGION_POINTS,
    Region,
    RegionPoints,
    budgeted,
    characteristic_region,
    closeup_region,
)
from tandemscan.pipeline.inspection.report import (
    MAX_CLOSEUPS,
    InspectedPart,
    ReportFacts,
    ReportStyle,
    StitchViews,
    build_report,
    failed_report,
    write_report,
)
from tandemscan.pipeline.inspection.tile_inspection import (
    AreaBounds,
    InspectedTiles,
    TiledInspection,
    UncertaintyField,
)
from tandemscan.pipeline.inspection.verdict import CloudAreas, VerdictContext, area_search, judge
from tandemscan.pipeline.io.cloud_io import CloudIOError, read_ply, read_ply_vertices
from tandemscan.pipeline.io.export import write_ply

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


@dataclass(frozen=True)
class InspectionSettings:
    """``[inspection]`` as the stages take it, built once where the configuration is read
    (:meth:`from_section`): how the cloud is aligned to CAD, what it is inspected and judged by, how the report
    draws."""

    alignment: AlignmentCriteria
    criteria: InspectionCriteria
    style: ReportStyle

    @classmethod
    def from_section(cls, section: InspectionConfig, template: InspectionTemplate | None = None) -> Self:
        """The stages' parameters of ``section``, with ``template``'s alignment where given
        (:meth:`InspectionTemplate.inspection_config`: its method and datum regions)."""
        if template is not None:
            section = template.inspection_config(section)
        return cls(AlignmentCriteria.from_section(section), InspectionCriteria.from_section(section),
                   ReportStyle.from_section(section))


@dataclass(frozen=True)
class Measurement:
    """What was measured, in the frame the function it is given to names (F for :func:`run_inspection`, W for
    :func:`align_and_inspect`), mm: the cloud's ``points_mm`` (N, 3), its unit ``normals`` (N, 3; None: none), what
    knows the points' ``uncertainty`` (None: the cloud states none, U = 0) and the scans for the stitching view
    (``stitching``; None: no such view)."""

    points_mm: np.ndarray
    normals: np.ndarray | None = None
    uncertainty: UncertaintyModel | None = None
    stitching: StitchViews | None = None


@dataclass(frozen=True)
class ReportOutput:
    """Where and what the inspection writes: the folder ``out_dir``, the report's ``facts``, and the JSON's file
    name (``json_name``; None leaves the JSON to the caller, who gets the same numbers as ``data``)."""

    out_dir: Path
    facts: ReportFacts = ReportFacts()
    json_name: str | None = "report.json"


@dataclass(frozen=True)
class AlignmentStart:
    """Where the alignment to CAD starts: ``T_F_W`` (where the job's anchor put the cloud; None: the cloud as
    given), described by ``description``; ``prior_T_F_W``, the placement that holds what the surface does not fix
    (None where the start is unknown); ``viewpoints_W``, the scanner positions (K, 3) mm the CAD's measured side
    is decided by (None: the cloud's normals)."""

    T_F_W: np.ndarray | None = None
    description: str = "as given"
    prior_T_F_W: np.ndarray | None = None
    viewpoints_W: np.ndarray | None = None


def run_inspection(measured: Measurement, part: InspectedPart, settings: InspectionSettings, output: ReportOutput,
                   alignment: Alignment | None = None, context: VerdictContext | None = None,
                   whole: TiledInspection | None = None) -> InspectionOutputs:
    """Inspect ``measured`` (frame F) against ``part`` by ``settings`` and write the report and the deviation PLY
    into ``output.out_dir``. The PLY carries the cloud's normals when given, else the closest CAD normals.
    ``alignment`` says how the points were placed in F (None: they came in F); ``context``: the installation and
    verification the verdict is made in (``verdict.judge``). The part's template characteristics (those without
    limits of their own under the criteria's tolerance, the general one) are evaluated, reported first and written
    as ``results.qif``. ``whole``: the tiled cloud ``measured`` is an even sample of (its frame W placed in F as
    ``alignment`` places the sample): the report's deviation figures (``as_measured``) and deviation areas are the
    whole cloud's and the deviation PLY holds every point of it, tile by tile (``tile_inspection.TiledInspection``,
    each point with the U of the sample's nearest), and so are the characteristics and the areas' close-ups, from its
    points in their regions (:func:`full_density`); U, the areas' guard band and their U (``verdict.area_search``,
    at the whole cloud's density) and the maps are the sample's."""
    criteria = settings.criteria
    template = part.template
    if template is not None:
        template = template.with_general_tolerance(criteria.tolerance_lower_mm, criteria.tolerance_upper_mm)
    surface = part.surface
    stitching = None if measured.stitching is None else measured.stitching.drawn()  # while the cloud is inspected
    p = as_points(measured.points_mm)
    closest = surface.closest(p)
    placed = alignment or Alignment("none", np.eye(4), 0.0, "the cloud as given")
    with ThreadPoolExecutor(1, thread_name_prefix="uncertainty") as pool:  # U beside the areas and the best fit
        u_of_points = pool.submit((measured.uncertainty or GivenUncertainty(0.0)).evaluate, p, closest.normals,
                                  criteria.decision_k, placed.T_F_W, placed.method,
                                  None if placed.excluded is None else ~placed.excluded, alignment_covariance(placed))
        result = inspect_cloud(p, surface, criteria, closest, find_areas=whole is None)  # else the tiles find them
        u = u_of_points.result()
    if measured.uncertainty is None:
        u = dataclasses.replace(u, notes=u.notes | {"cloud": "the cloud states no uncertainty: U = 0"})
    context = pose_context(placed, context or VerdictContext())
    out_dir = Path(output.out_dir)
    if whole is None:
        result = judge(result, u, criteria, context)
    else:  # the whole cloud's deviation figures, areas and PLY, tile by tile
        left_out = () if placed.excluded is None else sphere_balls(placed.spheres, settings.alignment)  # as the sample
        given = len(p) if placed.excluded is None else len(placed.excluded)  # the sample before the spheres left it
        per_sample_point = whole.count / max(given, 1)
        search = area_search(p, u, criteria, round(len(p) * per_sample_point))
        with whole.inspected(surface, placed.T_F_W, (criteria.tolerance_lower_mm, criteria.tolerance_upper_mm),
                             UncertaintyField.of(result.points_mm, u.expanded_mm), left_out, out_dir / DEVIATION_PLY,
                             AreaBounds(search.lower_mm, search.upper_mm, criteria.area_smoothing_mm,
                                        criteria.area_min_mm2)) as tiles:
            cloud = tiles.whole
            result = judge(result, u, criteria, context, CloudAreas(search, cloud.areas))
            nearby = full_density(tiles, template, measured_cloud(result, surface, u.expanded_mm), result.areas,
                                  per_sample_point)
        result = dataclasses.replace(result, stats=cloud.figures.stats, tolerance=cloud.figures.tolerance)
    if whole is None:
        nearby = Nearby(measured_cloud(result, surface, u.expanded_mm))
    with ThreadPoolExecutor(2, thread_name_prefix="inspection-outputs") as pool:  # beside the figures: the
        evaluated = None if template is None else pool.submit(  # characteristics and the file
            nearby.evaluate, template, criteria.rule)
        ply = None if whole is not None else pool.submit(
            write_ply,
            out_dir / DEVIATION_PLY,
            result.points_mm,
            measured.normals if measured.normals is not None else result.cad_normals,
            {"deviation_mm": result.deviations_mm, "uncertainty_mm": u.expanded_mm},
        )
        report = build_report(result, part, settings.style, output.facts, alignment=alignment, stitching=stitching,
                              characteristics=() if evaluated is None else evaluated,
                              surroundings=nearby.surroundings)
        html, js = write_report(report, out_dir, output.json_name)
    characteristics = () if evaluated is None else evaluated.result()
    qif = None if template is None else write_results(
        out_dir / RESULTS_FILE, measured_part(template, part.labels), characteristics, nearby.cloud.points_mm)
    return InspectionOutputs(result, report.data, html, js, out_dir / DEVIATION_PLY if ply is None else ply.result(),
                             characteristics, qif)


@dataclass(frozen=True)
class Nearby:
    """What the template's characteristics are evaluated on and the deviation areas' close-ups drawn from: the
    inspected ``cloud`` (F, mm) with, where it is a tiled cloud's points gathered by region
    (:func:`full_density`), each characteristic's ``rows`` of it, the ``steps`` each region was thinned by (1: every
    point) and the points around the largest areas by area id (``surroundings``; none: the close-ups draw the
    inspected points)."""

    cloud: MeasuredCloud
    rows: tuple[slice, ...] | None = None
    steps: tuple[int, ...] = ()
    surroundings: Mapping[int, Surroundings] = dataclasses.field(default_factory=dict)

    def evaluate(self, template: InspectionTemplate, rule: DecisionRule) -> tuple[CharacteristicResult, ...]:
        """``characteristics.evaluate`` of ``template`` on the cloud, each characteristic on its rows; one whose
        region was thinned says so in its method."""
        out = evaluate(template, self.cloud, rule, self.rows)
        return tuple(c if step == 1 else dataclasses.replace(
            c, method=f"{c.method}; on one in every {step} points of its region (the report's regions gather at "
            f"most {REGION_POINTS} points)") for c, step in zip(out, self.steps or (1,) * len(out), strict=True))


def full_density(tiles: InspectedTiles, template: InspectionTemplate | None, sample: MeasuredCloud,
                 areas: Sequence[DeviationArea], per_sample_point: float) -> Nearby:
    """The tiled cloud's points (``tiles``, every point, F mm) in each of ``template``'s characteristics' regions and
    around the first :data:`report.MAX_CLOSEUPS` of ``areas`` (``region_points``), within the regions' budget counted
    on the report's even ``sample`` of it (``per_sample_point`` points of the cloud each)."""
    surface = sample.surface
    specs = () if template is None else template.characteristics
    wanted = tuple(characteristic_region(spec, template, surface) for spec in specs)
    shown = tuple(areas[:MAX_CLOSEUPS])
    regions = budgeted((*wanted, *(closeup_region(a) for a in shown)), sample.points_mm, sample.triangle_ids,
                       per_sample_point, REGION_POINTS)
    names = [*(spec.id for spec in specs), *(f"close-up #{a.id}" for a in shown)]
    for r, name in zip(regions, names, strict=True):
        if r.step > 1:
            log.warning("%s: its region holds more points than the report gathers; one in every %d taken", name,
                        r.step)
    found = tiles.points_in(regions)
    own, around = found[: len(wanted)], found[len(wanted):]
    ends = np.cumsum([0, *(len(f) for f in own)]).tolist()
    return Nearby(RegionPoints.joined(own, 1).measured(surface), tuple(map(slice, ends[:-1], ends[1:])),
                  tuple(r.step for r in regions[: len(wanted)]),
                  {a.id: Surroundings(f.points_mm, f.deviations_mm, surface.closest(f.points_mm).normals if len(f)
                                      else np.zeros((0, 3))) for a, f in zip(shown, around, strict=True)})


def pose_context(alignment: Alignment, context: VerdictContext) -> VerdictContext:
    """``context`` with the alignment's ambiguity among its unsettled reasons where a rival pose is not ruled out and
    the deviations differ between the two (:attr:`RivalPose.unsettles_verdict`): the verdict is indeterminate."""
    rival = alignment.rival
    if rival is None or not rival.unsettles_verdict:
        return context
    why = (f"the cloud's pose on the CAD is ambiguous: {alignment.ambiguity}; which deviations are the part's is "
           "not proven")
    return dataclasses.replace(context, unsettled=(*context.unsettled, why))


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


def align_and_inspect(measured_W: Measurement, part: InspectedPart, settings: InspectionSettings,
                      output: ReportOutput, start: AlignmentStart = AlignmentStart(),
                      context: VerdictContext | None = None, whole: TiledInspection | None = None
                      ) -> InspectionOutputs:
    """Register a cloud measured in frame W (``measured_W``) to the CAD frame F by ``settings.alignment`` from
    ``start``, orient the CAD by the measured side (:func:`measured_side`: the start's scanner positions, else the
    cloud's normals), then inspect and write as :func:`run_inspection`. The points on reference spheres are left
    out of the inspection; the stitching views are mapped into F as well. A template aligned on datums
    (``part.template``) refines the fit on its datum patches (:func:`align_datums`; a tiled cloud's on every point
    in the patches' boxes, :func:`datum_points`). A failed alignment writes the
    report of a failed inspection (verdict "indeterminate", the reason) and returns it without a result.
    ``whole``: the tiled cloud ``measured_W`` is an even sample of (:func:`run_inspection`)."""
    surface = part.surface
    p = as_points(measured_W.points_mm)
    # a rigid motion changes no overlap: computed in W while the cloud is aligned and inspected
    views_W = None if measured_W.stitching is None else measured_W.stitching.started()
    try:
        alignment = align(surface, p, settings.alignment, start.T_F_W, start.description, start.prior_T_F_W,
                          toward_W=measured_W.normals)  # a scanner's normals face it: no point fits a wall's far side
    except AlignmentFailed as e:  # a failed inspection, with the reason on its report
        log.warning("%s", e)
        failed = failed_report(str(e), e.attempt, title=output.facts.title, meta=output.facts.meta)
        html, js = write_report(failed, output.out_dir, output.json_name)
        return InspectionOutputs(None, failed.data, html, js, None)
    template = part.template
    if template is not None and template.alignment.method == "datums":
        patches = [DatumPatch(d.feature, d.patch, template.patches[d.patch].min_mm, template.patches[d.patch].max_mm)
                   for d in template.alignment.datums]
        alignment = align_datums(surface, p if whole is None else datum_points(whole, patches, p, alignment.T_F_W),
                                 alignment, patches)
    keep = np.ones(len(p), bool) if alignment.excluded is None else ~alignment.excluded
    T = alignment.T_F_W
    log.info("aligned to CAD by %s: residual %.4f mm, %d points on reference spheres left out",
             alignment.method, alignment.residual_mm, int((~keep).sum()))
    surface, note = measured_side(surface, p, T, measured_W.normals, start.viewpoints_W)
    if note:
        facts = dataclasses.replace(output.facts, meta=dict(output.facts.meta) | {"CAD winding": note})
        output = dataclasses.replace(output, facts=facts)
    every = bool(keep.all())  # no copy of the cloud where no point is left out
    normals_W = None if measured_W.normals is None else (
        measured_W.normals if every else np.asarray(measured_W.normals)[keep])
    measured_F = Measurement(
        in_chunks(transform_points, T, p if every else p[keep]),
        None if normals_W is None else in_chunks(rotate_vectors, T, normals_W),
        measured_W.uncertainty,
        None if views_W is None else StitchViews(
            PlacedScans(views_W.before, T), None if views_W.after is None else PlacedScans(views_W.after, T),
            views_W.overlap))
    return run_inspection(measured_F, dataclasses.replace(part, surface=surface), settings, output, alignment, context,
                          whole)


def datum_points(whole: TiledInspection, patches: Sequence[DatumPatch], sample_W_mm: np.ndarray, T_F_W: np.ndarray
                 ) -> np.ndarray:
    """The tiled cloud's points (W, mm, every point, in its order) that ``T_F_W`` (the best fit) places in the datum
    ``patches``' boxes, within the regions' budget counted on its even sample ``sample_W_mm`` (``region_points``)."""
    regions = budgeted([Region.box(d.min_mm, d.max_mm) for d in patches], transform_points(T_F_W, sample_W_mm), None,
                       whole.count / len(sample_W_mm), REGION_POINTS)
    for d, r in zip(patches, regions, strict=True):
        if r.step > 1:
            log.warning("datum %s %r: its box holds more points than the report gathers; one in every %d taken",
                        d.feature, d.name, r.step)
    return whole.placed_in(T_F_W, regions)


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
    o = orient(np.asarray(surface.mesh.vertices), np.asarray(surface.mesh.triangles), ids, toward, by, surface.patches)
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


def inspect_files(cloud_path: Path | str, cad_path: Path | str, out_dir: Path | str, settings: InspectionSettings,
                  template: InspectionTemplate | None = None, labels: Mapping[str, str] | None = None,
                  point_uncertainty_mm: float | None = None, units: tuple[str, str] = ("mm", "mm")
                  ) -> InspectionOutputs:
    """Inspect a cloud file against a CAD mesh file; writes into ``out_dir``. The cloud is registered by
    ``settings.alignment`` from where it lies (within the first trim distance of its place on CAD); ``template``
    and ``labels`` as :class:`InspectedPart` holds them. The points' expanded uncertainty
    (k = ``settings.criteria.decision_k``, mm) is ``point_uncertainty_mm``, else the PLY's ``uncertainty_mm``
    property where it has one (a job's ``cloud_deviation.ply``), else none is known (0). ``units``: the CAD's
    and the cloud's file units (keys of ``units.MM_PER_UNIT``); files whose sizes disagree as files in different
    units do are refused (:func:`units.scale_mismatch`).

    Eight parameters: the two files and where to write, the settings, then what the operator states of the part
    and the files (template, labels, the points' uncertainty, the files' units), each optional."""
    try:
        points, normals = read_ply(cloud_path)
        mesh = read_mesh_file(Path(cad_path), what="CAD mesh", units=units[0])
    except (CloudIOError, PartMeshError) as e:
        raise InspectionError(str(e)) from e
    points = points * MM_PER_UNIT[units[1]]
    if mismatch := scale_mismatch(extent_mm(points), extent_mm(np.asarray(mesh.vertices))):
        raise InspectionError(f"{cloud_path}, {cad_path}: {mismatch}")
    own = point_uncertainty_mm
    if own is None and Path(cloud_path).suffix.lower() == ".ply":
        try:
            own = read_ply_vertices(cloud_path).get("uncertainty_mm")  # the file's unit, as its points
            own = None if own is None else own * MM_PER_UNIT[units[1]]
        except CloudIOError:  # a layout only Open3D reads: it has no such property for us
            own = None
    meta = {"cloud": str(cloud_path), "CAD mesh": str(cad_path), "points": str(len(points))}
    given = None if own is None else GivenUncertainty(np.asarray(own, float), settings.criteria.decision_k)
    part = InspectedPart(CadSurface(mesh), template, dict(labels or {}))
    return align_and_inspect(Measurement(points, normals, given), part, settings,
                             ReportOutput(Path(out_dir), ReportFacts(meta=meta)),
                             AlignmentStart(description="the cloud as given"))
