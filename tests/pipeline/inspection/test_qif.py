"""results.qif: a QIF 3.0 Results document per inspection with a template, valid against the QIF 3.0 schema
(../shared/qif), whose statuses, serial and per-point deviations read back as report.json has them; the same
from `tandemscan inspect --template --serial` on a cloud given 20 deg and 200 mm off CAD."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import numpy as np
import open3d as o3d
import pytest
from tandemscan.config.inspection_template import load_template, shipped_template
from tandemscan.config.models import InspectionConfig
from tandemscan.daemon.cli.inspect_cmd import main
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.inspection.inspection_job import InspectionSettings, Measurement, ReportOutput, run_inspection
from tandemscan.pipeline.inspection.qif import QIF_KINDS
from tandemscan.pipeline.inspection.report import InspectedPart
from test_characteristics import sampled_cloud

NS = {"q": "http://qifstandards.org/xsd/qif3"}
QIF_STATUS = {"PASS": "pass", "FAIL": "fail", "INDETERMINATE": "indeterminate", "NOT MEASURED": "not measured"}


def qif_statuses(path) -> tuple[dict[str, str], str | None, ET.Element]:
    """{characteristic id: status} of a results.qif (item name -> measurement status), the serial, the root."""
    root = ET.parse(path).getroot()
    items = root.find("q:Characteristics/q:CharacteristicItems", NS)
    item_names = {i.get("id"): i.find("q:Name", NS).text for i in items}
    out = {}
    for m in root.find("q:Results/q:MeasurementResultsSet/q:MeasurementResults/q:MeasuredCharacteristics/"
                       "q:CharacteristicMeasurements", NS):
        status = m.find("q:Status", NS)[0].text
        out[item_names[m.find("q:CharacteristicItemId", NS).text]] = QIF_STATUS[status]
    serial = root.find(".//q:ActualComponent/q:SerialNumber", NS)
    return out, None if serial is None else serial.text, root


@pytest.mark.slow
def test_results_qif_validates_and_reads_back_as_the_report(tmp_path, qif_schema):
    cloud = sampled_cloud("config/as-built-example.toml", (-430.0, 900.0, 600.0), (-270.0, 1100.0, 760.0), 1.0, 6)
    cfg = InspectionConfig(views=("right",), map_width_px=200, best_fit=False, regions=())
    part = InspectedPart(cloud.surface, load_template(shipped_template()),
                         {"serial": "SN-0042", "measuring_system": "simulated cell"})
    out = run_inspection(Measurement(cloud.points_mm), part, InspectionSettings.from_section(cfg),
                         ReportOutput(tmp_path))
    assert out.qif == tmp_path / "results.qif"
    qif_schema.validate(str(out.qif))
    statuses, serial, root = qif_statuses(out.qif)
    report = json.loads((tmp_path / "report.json").read_text())["inspection"]
    assert statuses == {c["id"]: c["status"] for c in report["characteristics"]}
    assert serial == "SN-0042" and "fail" in statuses.values() and "not measured" in statuses.values()
    assert root.find(".//q:Part/q:ModelNumber", NS).text == "TS-NOSE-3000"
    assert root.find(".//q:MeasurementDevice/q:Name", NS).text == "simulated cell"
    assert root.find(".//q:MeasurementResults/q:InspectionStatus/q:InspectionStatusEnum", NS).text == "FAIL"
    sp2 = next(c for c in out.characteristics if c.id == "SP-2")
    sets = {s.find("q:Attributes/q:AttributeStr", NS).get("value"): s
            for s in root.iter(f"{{{NS['q']}}}MeasuredPointSet")}
    dev = np.array(sets["SP-2"].find("q:Deviations", NS).text.split(), float)
    every = -(-len(sp2.point_ids) // 20_000)  # at most 20 000 points, every k-th
    assert len(dev) == int(sets["SP-2"].get("count")) == len(sp2.point_ids[::every]) > 10_000
    np.testing.assert_allclose(dev, sp2.deviations_mm[::every], atol=1e-4)
    kinds = {m.tag.split("}")[1] for m in root.iter() if m.tag.endswith("CharacteristicMeasurement")}
    assert kinds == {f"{QIF_KINDS[k]}CharacteristicMeasurement" for k in ("surface_profile", "flatness", "section")}


@pytest.mark.slow
def test_inspect_with_a_template_from_20_deg_and_200_mm_reaches_the_same_characteristics(tmp_path, qif_schema,
                                                                                           capsys):
    cloud = sampled_cloud("config/as-built-example.toml", (-1450.0, 0.0, 540.0), (1200.0, 1100.0, 980.0), 0.15, 8)
    cad = tmp_path / "nose.ply"
    o3d.io.write_triangle_mesh(str(cad), cloud.surface.mesh)
    axis = np.array([0.3, -0.5, 1.0]) / np.linalg.norm([0.3, -0.5, 1.0])
    T = F.from_rotvec([120.0, -100.0, 125.0], np.radians(20.0) * axis)
    assert np.linalg.norm(T[:3, 3]) == pytest.approx(200.0, abs=0.5)
    cell = tmp_path / "cell.toml"
    cell.write_text("[inspection]\nmap_width_px = 300\nviews = ['right']\n")
    results = {}
    for name, pose in (("in place", np.eye(4)), ("moved", T)):
        path = tmp_path / f"{name}.ply"
        o3d.io.write_point_cloud(str(path), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(
            F.transform_points(pose, cloud.points_mm))))
        out = tmp_path / name.replace(" ", "-")
        assert main([str(path), "--cad", str(cad), "--template", str(shipped_template()), "--serial", "SN-7",
                     "--out", str(out), "--no-best-fit", "--config", str(cell)]) == 0
        qif_schema.validate(str(out / "results.qif"))
        statuses, serial, _ = qif_statuses(out / "results.qif")
        report = json.loads((out / "report.json").read_text())["inspection"]
        assert serial == "SN-7" and statuses == {c["id"]: c["status"] for c in report["characteristics"]}
        results[name] = {c["id"]: c for c in report["characteristics"]}
    assert "SP-2" in capsys.readouterr().out
    for cid, c in results["in place"].items():
        moved = results["moved"][cid]
        assert moved["status"] == c["status"], cid
        assert moved["actual_mm"] == pytest.approx(c["actual_mm"], abs=0.02), cid
