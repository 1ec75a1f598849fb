"""``results.qif``: a job's characteristics as a QIF 3.0 Results document (ISO 23952:2020), what a plant's
quality system reads (docs/quality.md, "QIF results").

One document holds what the results need: the part (Product, its part number), the measuring system (the
cell, a measurement device), the characteristics' definitions, nominals and items (from the template), a
measurement plan that measures each of them, and the results: per characteristic its status, the measured
values (mm), the time and the device, the per-point deviations of each surface profile, the measured part's
serial number and the overall status. Millimetres throughout.

Kinds: surface profile -> ``SurfaceProfileCharacteristic``, flatness -> ``FlatnessCharacteristic``, section ->
``LineProfileCharacteristic`` (a profile of the section line), edge -> ``PointProfileCharacteristic`` (the
trimmed-edge point's profile). A profile's ``Value`` is the zone it needs (twice its largest distance from CAD),
its ``MaxValue`` / ``MinValue`` the signed extremes; flatness's ``Value`` is the flatness. Status: pass ->
PASS, fail -> FAIL; indeterminate (the decision rule could prove neither) and not measured -> the schema's
``OtherCharacteristicStatus`` with those words.
"""

from __future__ import annotations

import datetime as dt
import math
import uuid
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tandemscan.pipeline.inspection.characteristics import CharacteristicResult

QIF_NS = "http://qifstandards.org/xsd/qif3"
QIF_VERSION = "3.0.0"
RESULTS_FILE = "results.qif"
QIF_KINDS = {"surface_profile": "SurfaceProfile", "flatness": "Flatness", "section": "LineProfile",
             "edge": "PointProfile"}
STATUS_ENUM = {"pass": "PASS", "fail": "FAIL"}


@dataclass(frozen=True)
class MeasuredPart:
    """What the results name: the part number, its description, the serial (None: not given), the
    measuring system (the cell's name) and when it was measured (UTC)."""

    part_number: str
    description: str
    serial: str | None
    measuring_system: str
    measured_utc: dt.datetime


class _Ids:
    """QIF ids: increasing integers, the largest written as the document's ``idMax``."""

    def __init__(self) -> None:
        self.last = 0

    def next(self) -> str:
        self.last += 1
        return str(self.last)


def _sub(parent: ET.Element, tag: str, text: str | None = None, **attrs: str) -> ET.Element:
    e = ET.SubElement(parent, tag, attrs)
    if text is not None:
        e.text = text
    return e


def _mm(v: float) -> str:
    return f"{v:.6f}"


def _status(parent: ET.Element, tag: str, status: str, enum_tag: str, other_tag: str) -> None:
    s = _sub(parent, tag)
    if status in STATUS_ENUM:
        _sub(s, enum_tag, STATUS_ENUM[status])
    else:
        _sub(s, other_tag, status.upper())


def overall_status(results: Sequence[CharacteristicResult]) -> str:
    """The part's status: fail when any characteristic fails, pass when every one passes, else
    indeterminate."""
    statuses = [r.status for r in results]
    if "fail" in statuses:
        return "fail"
    return "pass" if statuses and all(s == "pass" for s in statuses) else "indeterminate"


def results_document(part: MeasuredPart, results: Sequence[CharacteristicResult], points_mm: np.ndarray
                     ) -> ET.ElementTree:
    """The QIF 3.0 document of ``results`` measured on ``part`` (module docstring); ``points_mm``: the
    inspected cloud (frame F) the results' point ids index."""
    ids = _Ids()
    root = ET.Element("QIFDocument", {"xmlns": QIF_NS, "versionQIF": QIF_VERSION, "idMax": "0"})
    _sub(root, "QPId", str(uuid.uuid4()))
    standards = _sub(root, "StandardsDefinitions", n="1")
    standard_id = ids.next()
    standard = _sub(standards, "Standard", id=standard_id)
    _sub(standard, "Organization").append(_enum("StandardsOrganizationEnum", "ISO"))
    _sub(standard, "Designator", "1101")
    units = _sub(_sub(root, "FileUnits"), "PrimaryUnits")
    linear = _sub(units, "LinearUnit")
    _sub(linear, "SIUnitName", "meter")
    _sub(linear, "UnitName", "mm")
    _sub(_sub(linear, "UnitConversion"), "Factor", "0.001")
    device_id = ids.next()
    devices = _sub(_sub(root, "MeasurementResources"), "MeasurementDevices", n="1")
    device = _sub(devices, "MeasurementDevice", id=device_id)
    _sub(device, "Name", part.measuring_system)
    _sub(device, "Description", "tandemscan: a structured-light scanner on a robot arm, tracked by a laser tracker")
    product = _sub(root, "Product")
    part_id = ids.next()
    qif_part = _sub(_sub(product, "PartSet", n="1"), "Part", id=part_id, label=part.part_number)
    _sub(qif_part, "ModelNumber", part.part_number)
    _sub(qif_part, "Version", part.description)
    _sub(_sub(product, "RootPart"), "Id", part_id)
    chars = _sub(root, "Characteristics")
    _sub(chars, "FormalStandardId", standard_id)
    definitions = _sub(chars, "CharacteristicDefinitions", n=str(len(results)))
    nominals = _sub(chars, "CharacteristicNominals", n=str(len(results)))
    items = _sub(chars, "CharacteristicItems", n=str(len(results)))
    item_ids = []
    for r in results:
        kind = QIF_KINDS[r.kind]
        def_id, nom_id, item_id = ids.next(), ids.next(), ids.next()
        d = _sub(definitions, f"{kind}CharacteristicDefinition", id=def_id)
        _sub(d, "Name", r.id)
        _sub(d, "ToleranceValue", _mm(r.upper_mm - r.lower_mm))
        if r.kind != "flatness":
            _sub(d, "UnequallyDisposedZone", _mm(r.upper_mm))
        n = _sub(nominals, f"{kind}CharacteristicNominal", id=nom_id)
        _sub(n, "CharacteristicDefinitionId", def_id)
        _sub(n, "Name", r.name)
        if r.kind == "section" and r.direction is not None:
            _sub(n, "Vector", " ".join(f"{v:.9f}" for v in r.direction))
        i = _sub(items, f"{kind}CharacteristicItem", id=item_id)
        _sub(i, "Name", r.id)
        _sub(_sub(i, "MeasurementDeviceIds", n="1"), "Id", device_id)
        _sub(i, "CharacteristicNominalId", nom_id)
        item_ids.append(item_id)
    _plan(root, device_id, item_ids)
    _results(root, ids, part, results, item_ids, device_id, points_mm)
    root.set("idMax", str(ids.last))
    ET.indent(root, space=" ")
    return ET.ElementTree(root)


def _enum(tag: str, text: str) -> ET.Element:
    e = ET.Element(tag)
    e.text = text
    return e


def _plan(root: ET.Element, device_id: str, item_ids: Sequence[str]) -> None:
    """The measurement plan: one step measuring and evaluating every characteristic item on the device."""
    step = _sub(_sub(_sub(_sub(root, "Plan"), "UnorderedPlanRoot"), "Steps", n="1"), "MeasureEvaluateSpecified")
    _sub(_sub(step, "PreferredResourceIds", n="1"), "Id", device_id)
    specified = _sub(step, "CharacteristicItemIds", n=str(len(item_ids)))
    for item_id in item_ids:
        _sub(specified, "Id", item_id)


def _results(root: ET.Element, ids: _Ids, part: MeasuredPart, results: Sequence[CharacteristicResult],
             item_ids: Sequence[str], device_id: str, points_mm: np.ndarray) -> None:
    out = _sub(root, "Results")
    measured = _sub(_sub(out, "MeasurementResultsSet", n="1"), "MeasurementResults", id=ids.next())
    _sub(measured, "ThisResultsInstanceQPId", str(uuid.uuid4()))
    profiles = [r for r in results if r.kind == "surface_profile" and len(r.deviations_mm)]
    if profiles:
        sets = _sub(measured, "MeasuredPointSets", n=str(len(profiles)))
        for r in profiles:
            _point_set(sets, ids.next(), r, points_mm)
    component_id = ids.next()
    when = part.measured_utc.astimezone(dt.UTC).isoformat(timespec="seconds").replace("+00:00", "Z")
    measurements = _sub(_sub(measured, "MeasuredCharacteristics"), "CharacteristicMeasurements",
                        n=str(len(results)))
    for r, item_id in zip(results, item_ids, strict=True):
        m = _sub(measurements, f"{QIF_KINDS[r.kind]}CharacteristicMeasurement", id=ids.next())
        _status(m, "Status", r.status, "CharacteristicStatusEnum", "OtherCharacteristicStatus")
        _sub(m, "CharacteristicItemId", item_id)
        _sub(m, "TimeStamp", when)
        _sub(m, "ActualComponentId", component_id)
        _sub(_sub(m, "MeasurementDeviceIds", n="1"), "Id", device_id)
        if not math.isfinite(r.actual_mm):
            continue
        if r.kind == "flatness":
            _sub(m, "Value", _mm(r.actual_mm))
            continue
        _sub(m, "Value", _mm(2.0 * max(abs(r.worst_plus_mm), abs(r.worst_minus_mm))))
        _sub(m, "MaxValue", _mm(r.worst_plus_mm))
        _sub(m, "MinValue", _mm(r.worst_minus_mm))
    _status(measured, "InspectionStatus", overall_status(results), "InspectionStatusEnum", "OtherInspectionStatus")
    _sub(_sub(measured, "ActualComponentIds", n="1"), "Id", component_id)
    component = _sub(_sub(_sub(out, "ActualComponentSets", n="1"), "ActualComponentSet", n="1"), "ActualComponent",
                     id=component_id)
    if part.serial is not None:
        _sub(component, "SerialNumber", part.serial)
    _status(component, "Status", overall_status(results), "InspectionStatusEnum", "OtherInspectionStatus")


MAX_PROFILE_POINTS = 20_000  # a surface profile's per-point deviations: an even subsample of at most this many


def _point_set(parent: ET.Element, set_id: str, r: CharacteristicResult, points_mm: np.ndarray) -> None:
    """A surface profile's points (frame F) and their deviations from CAD (mm), at most
    :data:`MAX_PROFILE_POINTS` of them (every k-th), named by the characteristic's id."""
    step = max(1, -(-len(r.point_ids) // MAX_PROFILE_POINTS))
    ids, dev = r.point_ids[::step], r.deviations_mm[::step]
    s = _sub(parent, "MeasuredPointSet", id=set_id, count=str(len(ids)))
    attrs = _sub(s, "Attributes", n="1")
    _sub(attrs, "AttributeStr", name="characteristic", value=r.id)
    _sub(s, "Points", " ".join(f"{v:.4f}" for v in points_mm[ids].ravel()))
    _sub(s, "Compensated", "false")  # a scanner's points: no probe radius to compensate
    _sub(s, "Deviations", " ".join(f"{v:.4f}" for v in dev))


def write_results(path: Path | str, part: MeasuredPart, results: Sequence[CharacteristicResult],
                  points_mm: np.ndarray) -> Path:
    """Write ``results.qif`` (or ``path``) for ``results`` measured on ``part`` (``points_mm``: the inspected
    cloud, frame F); returns the path."""
    path = Path(path)
    results_document(part, results, points_mm).write(path, encoding="UTF-8", xml_declaration=True)
    return path
