"""``tandemscan inspect``: a report for any cloud; bad input is one clear error line and exit status 2."""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d
import pytest
from tandemscan.daemon.cli.inspect_cmd import main


@pytest.fixture
def files(tmp_path):
    mesh = o3d.geometry.TriangleMesh.create_box(400.0, 200.0, 100.0)
    mesh.compute_triangle_normals()
    cad = tmp_path / "box.stl"
    o3d.io.write_triangle_mesh(str(cad), mesh)
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(0, 400, 4000), rng.uniform(0, 200, 4000), 100.0 + rng.normal(0.02, 0.03, 4000)]
    cloud = tmp_path / "cloud.ply"
    o3d.io.write_point_cloud(str(cloud), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)))
    cfg = tmp_path / "cell.toml"
    cfg.write_text("[inspection]\nmap_width_px = 250\nregions = []\nviews = ['top']\n")
    return cloud, cad, cfg


@pytest.mark.slow
def test_inspect_writes_report_and_deviation_cloud(files, tmp_path, capsys):
    cloud, cad, cfg = files
    out = tmp_path / "out"
    assert main([str(cloud), "--cad", str(cad), "--tolerance", "0.05", "--out", str(out), "--config", str(cfg),
                 "--alignment", "none"]) == 0
    said = capsys.readouterr().out
    assert "4000 points" in said and str(out / "report.html") in said
    data = json.loads((out / "report.json").read_text())["inspection"]
    assert data["as_measured"]["tolerance"]["upper_mm"] == 0.05
    assert data["as_measured"]["stats"]["mean_mm"] == pytest.approx(0.02, abs=0.003)
    assert "<img" in (out / "report.html").read_text()
    dev = o3d.t.io.read_point_cloud(str(out / "cloud_deviation.ply")).point.deviation_mm.numpy().ravel()
    assert len(dev) == 4000 and abs(dev.mean() - 0.02) < 0.003


@pytest.mark.parametrize(
    "case, needle",
    [("missing cloud", "cloud file not found"), ("missing cad", "CAD mesh file not found"),
     ("garbage cloud", "not a PLY file"), ("cloud as cad", "no triangles"),
     ("bad tolerance", "--tolerance must be > 0")],
)
def test_bad_input_is_one_error_line_and_exit_2(files, tmp_path, capsys, case, needle):
    cloud, cad, cfg = files
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"this is not a point cloud\n")
    args = {
        "missing cloud": [str(tmp_path / "nope.ply"), "--cad", str(cad)],
        "missing cad": [str(cloud), "--cad", str(tmp_path / "nope.stl")],
        "garbage cloud": [str(garbage), "--cad", str(cad)],
        "cloud as cad": [str(cloud), "--cad", str(cloud)],
        "bad tolerance": [str(cloud), "--cad", str(cad), "--tolerance", "-1"],
        "rps without spheres": [str(cloud), "--cad", str(cad), "--alignment", "rps", "--config", str(cfg)],
        "unknown datum": [str(cloud), "--cad", str(cad), "--datum", "wing", "--config", str(cfg)],
    }[case]
    assert main([*args, "--out", str(tmp_path / "o")]) == 2
    said = capsys.readouterr()
    assert said.out == "" and said.err.startswith("tandemscan inspect: error:") and needle in said.err
    assert len(said.err.strip().splitlines()) == 1


def closed_box(tmp_path, rng, per_face):
    """The CAD of a 400 x 200 x 100 mm box written as STL, and ``per_face`` points uniform on each of its faces."""
    mesh = o3d.geometry.TriangleMesh.create_box(400.0, 200.0, 100.0)
    mesh.compute_triangle_normals()
    cad = tmp_path / "box.stl"
    o3d.io.write_triangle_mesh(str(cad), mesh)
    faces = []
    for axis, size in ((0, 400.0), (1, 200.0), (2, 100.0)):
        for at in (0.0, size):
            p = rng.uniform([0, 0, 0], [400.0, 200.0, 100.0], (per_face, 3))
            p[:, axis] = at
            faces.append(p)
    return cad, np.vstack(faces)


@pytest.mark.slow
def test_misplaced_cloud_is_aligned_and_its_dent_reported_in_cad_coordinates(tmp_path, capsys):
    """A closed box scanned all round with a 0.3 mm dent, given 5 deg and 40 mm off CAD: the best fit puts
    it back, the report fails it with one lower area at the dent (CAD mm)."""
    from tandemscan.pipeline.geometry import frames as F

    rng = np.random.default_rng(1)
    cad, pts = closed_box(tmp_path, rng, 15_000)
    dent = np.linalg.norm(pts - [150.0, 80.0, 100.0], axis=1)
    pts[:, 2] -= np.where(dent < 30.0, 0.15 * (1.0 + np.cos(np.pi * dent / 30.0)), 0.0)  # top face, 0.3 mm deep
    pts += rng.normal(0, 0.01, pts.shape)
    off = F.from_rotvec([25.0, -20.0, 25.0], np.radians([2.0, -3.0, 3.0]))
    cloud = tmp_path / "moved.ply"
    o3d.io.write_point_cloud(str(cloud), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(
        F.transform_points(off, pts))))
    cfg = tmp_path / "cell.toml"
    cfg.write_text("[inspection]\nmap_width_px = 250\nregions = []\nviews = ['top']\nreference_spheres = []\n")
    out = tmp_path / "out"
    assert main([str(cloud), "--cad", str(cad), "--out", str(out), "--config", str(cfg)]) == 0
    assert capsys.readouterr().out.startswith("FAIL: 1 areas beyond the band; aligned by best-fit")
    ins = json.loads((out / "report.json").read_text())["inspection"]
    assert ins["verdict"] == "fail" and ins["alignment"]["method"] == "best-fit"
    np.testing.assert_allclose(np.array(ins["alignment"]["T_F_W"]) @ off, np.eye(4), atol=1e-3)
    (area,) = ins["deviations"]
    assert area["side"] == "lower" and area["id"] == 1 and area["points"] > 50
    np.testing.assert_allclose(area["centroid_mm"], [150.0, 80.0, 100.0], atol=1.5)
    assert area["extreme_mm"] == pytest.approx(-0.3, abs=0.03) and area["mean_mm"] < -0.1
    html = (out / "report.html").read_text()
    assert 'id="verdict" class="verdict fail"' in html and 'id="deviations"' in html


def test_unreadable_file_gives_only_our_line_at_fd_level(files, tmp_path, capfd):
    """Open3D's own warnings (printed by C++, not via Python) must not add lines around ours: capfd
    captures the process's file descriptors, so C-level prints would show."""
    _, cad, _ = files
    garbage = tmp_path / "garbage.pcd"
    garbage.write_bytes(b"this is not a point cloud\n")
    assert main([str(garbage), "--cad", str(cad), "--out", str(tmp_path / "o")]) == 2
    said = capfd.readouterr()
    lines = [ln for ln in (said.out + said.err).splitlines() if ln.strip()]
    assert len(lines) == 1, lines
    assert lines[0].startswith("tandemscan inspect: error:") and "no points could be read" in lines[0]


def test_registered_in_the_main_cli(files, tmp_path, capsys):
    from tandemscan.daemon.cli import main as tandemscan

    cloud, cad, cfg = files
    assert tandemscan(["inspect", str(tmp_path / "nope.ply"), "--cad", str(cad)]) == 2
    assert "cloud file not found" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:  # argparse: --cad is required
        tandemscan(["inspect", str(cloud)])
    assert e.value.code == 2


@pytest.mark.slow
def test_point_uncertainty_gives_the_same_decisions_in_place_and_20_deg_200_mm_away(tmp_path, capsys):
    """A closed box with a bump proven out (0.8 mm), one proven in (0.25 mm) and one within U of the +-0.5 mm
    limit (0.5 mm), its points' U 0.3 mm stated by --point-uncertainty-mm: in place (no alignment) and turned
    20 deg and moved 200 mm (best fit), the same areas with the same decisions; the deviation PLY carries U."""
    from tandemscan.pipeline.geometry import frames as F

    rng = np.random.default_rng(4)
    cad, pts = closed_box(tmp_path, rng, 20_000)
    top = pts[:, 2] == 100.0
    for centre, height in (((80.0, 60.0), 0.8), ((200.0, 140.0), 0.25), ((320.0, 60.0), 0.5)):
        r = np.linalg.norm(pts[:, :2] - centre, axis=1) / 35.0
        pts[:, 2] += np.where(top & (r < 1.0), 0.5 * height * (1.0 + np.cos(np.pi * np.clip(r, 0, 1))), 0.0)
    pts += rng.normal(0, 0.01, pts.shape)
    cfg = tmp_path / "cell.toml"
    cfg.write_text("[inspection]\nmap_width_px = 250\nregions = []\nviews = ['top']\nreference_spheres = []\n"
                   "tolerance_lower_mm = -0.5\ntolerance_upper_mm = 0.5\n")
    decisions = {}
    off = F.from_rotvec([200.0, 0.0, 0.0], np.radians([0.0, 0.0, 20.0]))
    for name, T, alignment in (("in-place", np.eye(4), "none"), ("moved", off, "best-fit")):
        cloud = tmp_path / f"{name}.ply"
        o3d.io.write_point_cloud(str(cloud), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(
            F.transform_points(T, pts))))
        out = tmp_path / name
        assert main([str(cloud), "--cad", str(cad), "--out", str(out), "--config", str(cfg), "--alignment",
                     alignment, "--point-uncertainty-mm", "0.3"]) == 0
        ins = json.loads((out / "report.json").read_text())["inspection"]
        decisions[name] = sorted((round(a["centroid_mm"][0] / 40.0), a["decision"]) for a in ins["deviations"])
        assert ins["verdict"] == "fail" and ins["decision_rule"] == {"name": "iso14253-1", "k": 2.0}
        assert ins["uncertainty"]["median_mm"] == pytest.approx(0.3)
        u = o3d.t.io.read_point_cloud(str(out / "cloud_deviation.ply")).point.uncertainty_mm.numpy().ravel()
        assert len(u) == len(pts) and np.allclose(u, 0.3)
    assert decisions["in-place"] == decisions["moved"] == [(2, "nonconforming"), (8, "indeterminate")]
    assert capsys.readouterr().out.startswith("FAIL")


@pytest.mark.slow
def test_a_second_inspection_replaces_the_report_whole(files, tmp_path):
    """report.json and report.html are replaced, not rewritten in place: a reader that opened them before the
    next inspection into the same folder reads the whole old report (a crash mid-write leaves the old or the new
    file, never half of one)."""
    cloud, cad, cfg = files
    out = tmp_path / "out"
    args = [str(cloud), "--cad", str(cad), "--out", str(out), "--config", str(cfg), "--alignment", "none"]
    assert main([*args, "--tolerance", "0.05"]) == 0
    old = {name: (out / name).read_bytes() for name in ("report.json", "report.html")}
    readers = {name: open(out / name, "rb") for name in old}  # noqa: SIM115 - closed below
    try:
        assert main([*args, "--tolerance", "0.08"]) == 0
        for name, reader in readers.items():
            assert reader.read() == old[name], name  # the old file, whole, for whoever had it open
    finally:
        for reader in readers.values():
            reader.close()
    new = json.loads((out / "report.json").read_text())["inspection"]
    assert new["as_measured"]["tolerance"]["upper_mm"] == 0.08
    assert not list(out.glob("*.part"))
