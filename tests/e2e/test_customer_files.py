"""A new customer's files through the CLI (docs/inspection.md, docs/planning.md): a CAD or part mesh in metres is
named as such with the option that reads it (exit 2, one line), and read with that option the defects come out
with their sign; the file names may be in any script."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from tandemscan.daemon.cli import main
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.io.export import write_ply
from tandemscan.sim_drivers.generated_parts import CadExport, pocket_box

T_W_F = F.from_rotvec([40.0, -30.0, 20.0], np.radians([3.0, -2.0, 8.0]))  # the cloud as a scanner left it


@pytest.fixture(scope="module")
def pocket():
    part = pocket_box()
    p_F, n_F = part.measured(5000, 0.01, np.random.default_rng(11))
    return part, F.transform_points(T_W_F, p_F), F.rotate_vectors(T_W_F, n_F)


@pytest.fixture()
def cell(tmp_path):
    cfg = tmp_path / "cell.toml"
    cfg.write_text("[inspection]\nmap_width_px = 160\nviews = ['top']\nreference_spheres = []\nbest_fit = false\n")
    return cfg


def inspect(tmp_path, cell, cloud, cad, *extra):
    out = tmp_path / "out"
    return main(["inspect", str(cloud), "--cad", str(cad), "--out", str(out), "--config", str(cell),
                 "--tolerance", "0.2", "--point-uncertainty-mm", "0.02", *extra]), out


def sides_at_defects(part, report) -> list[str]:
    areas = json.loads(report.read_text(encoding="utf-8"))["inspection"]["deviations"]
    return [",".join(sorted({a["side"] for a in areas
                             if np.linalg.norm(np.subtract(a["centroid_mm"], d.centre_mm)) < 10.0})) or "none"
            for d in part.defects]


def test_a_cad_in_metres_is_named_with_its_option_and_then_read(tmp_path, cell, pocket, capsys):
    part, p_W, n_W = pocket
    cad = CadExport(scale=0.001).write(part, tmp_path / "pocket-m.stl")
    cloud = write_ply(tmp_path / "scan.ply", p_W, n_W)
    rc, out = inspect(tmp_path, cell, cloud, cad)
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and not (out / "report.json").exists()
    assert re.search(r"the CAD 0.9 x 0.6 x 0.35 mm: 10\d\d times larger", err), err
    assert err.endswith("if the CAD is in metres, give --cad-units m ([part] mesh_units in a job)"), err
    rc, out = inspect(tmp_path, cell, cloud, cad, "--cad-units", "m")
    assert rc == 0
    assert sides_at_defects(part, out / "report.json") == ["lower", "upper", "upper"]


def test_a_cloud_in_metres_is_named_with_its_option(tmp_path, cell, pocket, capsys):
    part, p_W, _ = pocket
    cad = CadExport().write(part, tmp_path / "pocket.ply")
    cloud = tmp_path / "scan.xyz"
    np.savetxt(cloud, p_W / 1000.0, fmt="%.7f")
    rc, _ = inspect(tmp_path, cell, cloud, cad)
    assert rc == 2 and "if the cloud is in metres, give --cloud-units m" in capsys.readouterr().err


def test_a_part_in_metres_is_named_by_plan_and_planned_with_its_unit(tmp_path, capsys):
    mesh = CadExport(scale=0.001).write(pocket_box(), tmp_path / "pocket-m.stl")
    assert main(["plan", "--part", str(mesh), "--out", str(tmp_path / "plan.toml")]) == 2
    err = capsys.readouterr().err
    assert "the part is 0.9 x 0.6 x 0.35 mm, far smaller than the cell measures" in err
    assert "give --part-units m" in err and not (tmp_path / "plan.toml").exists()
    assert main(["plan", "--part", str(mesh), "--part-units", "m", "--out", str(tmp_path / "plan.toml")]) == 0
    report = json.loads((tmp_path / "plan-report.json").read_text())
    assert report["scans"] > 10 and report["coverage"]["coverage_pct"] > 90.0


@pytest.mark.parametrize("cad_name, cloud_name", [("Flügel_Ø500 – prüf.obj", "Scan Flügel №1.ply"),
                                                  ("翼セグメント.stl", "点群.xyz")])
def test_file_names_in_any_script(tmp_path, cell, pocket, cad_name, cloud_name):
    part, p_W, n_W = pocket
    cad = CadExport(soup=True).write(part, tmp_path / cad_name)
    cloud = tmp_path / cloud_name
    if cloud.suffix == ".ply":
        write_ply(cloud, p_W, n_W)
    else:
        np.savetxt(cloud, p_W, fmt="%.5f")
    rc, out = inspect(tmp_path, cell, cloud, cad)
    assert rc == 0
    assert sides_at_defects(part, out / "report.json") == ["lower", "upper", "upper"]
    assert cloud_name in (out / "report.html").read_text(encoding="utf-8")
