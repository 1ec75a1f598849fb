"""Alignment to CAD from anywhere and the sign on any mesh, on generated parts of different kinds
(sim_drivers/generated_parts.py): a cylinder arch with an open, inward-wound mesh, a long extrusion, a closed
double-curved part, each given from random starts up to 30 deg / 300 mm about the CAD origin; what the
measured surface does not fix (a cylinder, a plane) named and held; a failed alignment a failed inspection."""

from __future__ import annotations

import json
import re

import numpy as np
import open3d as o3d
import pytest
from tandemscan.config.models import InspectionConfig
from tandemscan.daemon.cli.inspect_cmd import main
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.inspection.alignment import AlignmentCriteria, AlignmentFailed, align, fit_to_surface
from tandemscan.pipeline.inspection.cad_orientation import consistent_winding, orient
from tandemscan.pipeline.inspection.deviation_maps import MapPoints, View, deviation_norm, render_view
from tandemscan.pipeline.inspection.inspect import CadSurface, InspectionCriteria, inspect_cloud
from tandemscan.pipeline.inspection.inspection_job import measured_side
from tandemscan.pipeline.io.export import write_ply
from tandemscan.sim_drivers.generated_parts import PARTS, arch_panel, random_misplacement
from tandemscan.sim_drivers.inspection_score import alignment_error

CFG = InspectionConfig(reference_spheres=(), regions=())


def centre_of(mesh) -> np.ndarray:
    v = np.asarray(mesh.vertices)
    return 0.5 * (v.min(axis=0) + v.max(axis=0))


def found_with_the_right_sign(part, areas) -> None:
    """Every seeded defect is one area on its side: centroid within 10 mm, extreme within 0.03 mm."""
    for d in part.defects:
        side = "upper" if d.depth_mm > 0 else "lower"
        near = [a for a in areas if np.linalg.norm(np.subtract(a.centroid_mm, d.centre_mm)) < 10.0]
        assert near and all(a.side == side for a in near), (d, [(a.side, a.centroid_mm) for a in areas])
        assert max(near, key=lambda a: abs(a.extreme_mm)).extreme_mm == pytest.approx(d.depth_mm, abs=0.03)


def inspect_from(part, surface, p_W, n_W, T_W_F):
    """The product's path without the pictures: align from the cloud as given, orient the CAD by the cloud's
    normals, inspect; the alignment's error against the truth at the CAD's centre."""
    a = align(surface, p_W, AlignmentCriteria.from_section(CFG))
    oriented, note = measured_side(surface, p_W, a.T_F_W, n_W, None)
    res = inspect_cloud(F.transform_points(a.T_F_W, p_W), oriented, InspectionCriteria.from_section(CFG))
    return a, alignment_error(a.T_F_W, F.invert(T_W_F), centre_of(part.mesh)), res, note


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(PARTS))
def test_five_random_starts_align_and_find_the_defects_with_their_sign(name):
    part = PARTS[name]()
    surface = CadSurface(part.mesh)
    rng = np.random.default_rng(sum(map(ord, name)))
    p_F, n_F = part.measured(20_000, 0.01, rng)
    aligned = 0
    for _ in range(5):
        T_W_F = random_misplacement(rng)
        try:
            a, (mm, deg), res, note = inspect_from(part, surface, F.transform_points(T_W_F, p_F),
                                                   F.rotate_vectors(T_W_F, n_F), T_W_F)
        except AlignmentFailed as e:  # allowed, with its reason
            assert str(e).startswith("alignment to CAD failed:")
            continue
        assert mm < 0.05 and deg < 0.005, (name, mm, deg)
        assert a.free_directions == () and a.inlier_share > 0.95
        found_with_the_right_sign(part, res.areas)
        assert bool(note) == (name == "arch")  # the arch's file is wound toward its axis: said, and turned
        aligned += 1
    assert aligned >= 4  # failing is allowed with a reason, not as the rule


def test_arch_from_a_far_start_is_aligned_and_its_dent_is_a_dent():
    """The issue's panel: the open mesh wound toward the axis, the cloud 25 deg and 250 mm off about the CAD
    origin (the crown 1.6 m up moves 0.9 m): aligned, the dent lower and the bulges upper."""
    part = arch_panel()
    surface = CadSurface(part.mesh)
    rng = np.random.default_rng(7)
    p_F, n_F = part.measured(30_000, 0.01, rng)
    T_W_F = F.from_rotvec([150.0, -200.0, 0.0], np.radians(25.0) * np.array([0.6, 0.0, 0.8]))
    a, (mm, deg), res, note = inspect_from(part, surface, F.transform_points(T_W_F, p_F),
                                           F.rotate_vectors(T_W_F, n_F), T_W_F)
    assert mm < 0.05 and deg < 0.005, (mm, deg)
    assert "winding disagrees with cloud normals" in note
    found_with_the_right_sign(part, res.areas)
    cov = a.covariance
    assert cov.shape == (6, 6) and np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)
    assert np.sqrt(cov[:3, :3].diagonal()).max() < 0.01  # 30 000 points of 0.01 mm noise: microns
    assert np.linalg.norm(np.subtract(a.covariance_centre_F_mm, p_F.mean(axis=0))) < 50.0


def cylinder_strip(rng, n=6000):
    """Points of the arch's plain middle (no pad, no edge: a piece of a cylinder), outward normals (F); the
    mesh in 20 mm facets (coarser facets would themselves fix the turn about the axis)."""
    part = arch_panel(step_mm=20.0)
    p, n_ = part.measured(60_000, 0.005, rng)
    keep = (np.abs(p[:, 0] + 1500.0) < 300.0) & (np.abs(p[:, 1]) < 1200.0)  # clear of the defects
    return part, p[keep][:n], n_[keep][:n]


def test_a_cylinder_leaves_its_axis_free_named_and_held_by_the_prior():
    """A plain piece of the barrel fixes neither the slide along its axis nor the turn about it: the fit names
    both and keeps them where the prior (the job's placement) has them, instead of drifting off (the issue's
    633 mm); the other four directions are fitted."""
    rng = np.random.default_rng(3)
    part, p_F, _ = cylinder_strip(rng)
    surface = CadSurface(part.mesh)
    prior = F.from_rotvec([40.0, 3.0, -2.0], np.radians([0.05, 0.0, 0.0]))  # 40 mm along, 0.05 deg about the axis
    a = fit_to_surface(surface, p_F, prior, AlignmentCriteria.from_section(CFG), "the anchor", prior)
    assert len(a.free_directions) == 2
    assert any(w.startswith("translation along (+1.000, +0.000, +0.000)") or
               w.startswith("translation along (-1.000") for w in a.free_directions), a.free_directions
    assert any(w.startswith("rotation about the axis along (+1.000") or w.startswith("rotation about the axis "
               "along (-1.000") for w in a.free_directions), a.free_directions
    (through,) = [re.search(r"through \((.*), (.*), (.*)\) mm", w) for w in a.free_directions if "through" in w]
    assert abs(float(through[2])) < 5.0 and abs(float(through[3]) + 600.0) < 5.0  # the axis: y = 0, z = -600
    moved = a.T_F_W @ F.invert(prior)
    assert abs(F.transform_points(moved, p_F.mean(axis=0)[None])[0][0] - p_F.mean(axis=0)[0]) < 1.0
    d = surface.signed_distance(F.transform_points(a.T_F_W, p_F))
    assert np.abs(d).max() < 0.05  # the fixed directions are fitted: the points lie on the surface
    cov = a.covariance  # zero along the free directions
    basis = np.array([[1.0, 0, 0, 0, 0, 0]])
    assert float((basis @ cov @ basis.T)[0, 0]) < 1e-12


def test_a_cloud_far_from_its_cad_fails_with_the_reason(tmp_path, capsys):
    """``tandemscan inspect`` of a cloud that is not on its CAD: one line "not completed", exit 5, and a
    report.html and report.json whose verdict is "indeterminate" with the reason."""
    part = arch_panel()
    mesh_file = tmp_path / "arch.ply"
    o3d.io.write_triangle_mesh(str(mesh_file), part.mesh)
    rng = np.random.default_rng(4)
    blob = rng.normal(0.0, 300.0, (3000, 3)) + [0.0, 0.0, 5000.0]  # a cloud of nothing, 3 m above the panel
    cloud = write_ply(tmp_path / "blob.ply", blob)
    cfg = tmp_path / "cell.toml"
    cfg.write_text("[inspection]\nmap_width_px = 200\nregions = []\nviews = ['top']\nreference_spheres = []\n")
    out = tmp_path / "out"
    assert main([str(cloud), "--cad", str(mesh_file), "--out", str(out), "--config", str(cfg)]) == 5
    said = capsys.readouterr()
    assert said.out == "" and len(said.err.strip().splitlines()) == 1
    assert said.err.startswith("tandemscan inspect: not completed: alignment to CAD failed:")
    data = json.loads((out / "report.json").read_text())["inspection"]
    assert data["verdict"] == "indeterminate" and data["reason"].startswith("alignment to CAD failed")
    html = (out / "report.html").read_text()
    assert 'class="verdict indeterminate"' in html and "alignment to CAD failed" in html


def test_winding_made_consistent_and_turned_by_the_measured_side():
    part = arch_panel(step_mm=200.0)
    V, T = np.asarray(part.mesh.vertices), np.asarray(part.mesh.triangles).copy()
    rng = np.random.default_rng(5)
    mess = rng.uniform(size=len(T)) < 0.4
    T[mess] = T[mess][:, ::-1]
    flip, label = consistent_winding(T)
    turned = np.where(flip[:, None], T[:, ::-1], T)
    n = np.cross(V[turned[:, 1]] - V[turned[:, 0]], V[turned[:, 2]] - V[turned[:, 0]])
    same = np.einsum("ij,ij->i", n, part.outward) > 0
    assert label.max() == 0 and (same.all() or not same.any())  # one patch, one way
    # the measured side decides which way: by the scanner's side (outside the barrel) ...
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V), o3d.utility.Vector3iVector(T))
    p, normals = part.measured(2000, 0.0, rng)
    ids = CadSurface(mesh).closest(p).triangle_ids
    o = orient(V, T, ids, normals, "cloud normals")
    turned = np.where(o.reversed[:, None], T[:, ::-1], T)
    n = np.cross(V[turned[:, 1]] - V[turned[:, 0]], V[turned[:, 2]] - V[turned[:, 0]])
    assert (np.einsum("ij,ij->i", n, part.outward) > 0).all() and o.by == "cloud normals"
    assert "winding disagrees with cloud normals" in o.note
    # ... the same from scanner positions 1 m outside; without a measured side the file's majority stays
    eyes = p[::50] + 1000.0 * normals[::50]
    oriented, note = measured_side(CadSurface(mesh), p, np.eye(4), None, eyes)
    assert np.array_equal(oriented.reversed, o.reversed) and "scanner positions" in note
    assert not orient(V, T).reversed[~mess].any() or not orient(V, T).reversed[mess].any()
    # a closed mesh is decided by its volume, and an outward one is left as it is
    part = PARTS["extrusion"]()
    assert not orient(np.asarray(part.mesh.vertices), np.asarray(part.mesh.triangles), ids[:0], normals[:0]).note


def test_maps_draw_an_open_panel_from_outside_and_inside():
    """The colour maps draw the measured points from whichever side the camera sees the panel; a wall of a
    thin closed box behind the near one stays hidden."""
    part = arch_panel(step_mm=100.0)
    surface = CadSurface(part.mesh)  # wound toward the axis as the file is: no matter for the maps
    rng = np.random.default_rng(6)
    p, _ = part.measured(20_000, 0.0, rng)
    cp = surface.closest(p)
    norm = deviation_norm(-0.1, 0.1)
    drawn = MapPoints(p, cp.signed_mm, cp.normals)
    outside = render_view(surface, drawn, View("top", (0.0, 0.0, -1.0), (0.0, 1.0, 0.0)), norm, 200)
    inside = render_view(surface, drawn, View("bottom", (0.0, 0.0, 1.0), (0.0, 1.0, 0.0)), norm, 200)
    assert outside.coloured_px > 5000 and inside.coloured_px > 0.8 * outside.coloured_px
    box = o3d.geometry.TriangleMesh.create_box(400.0, 300.0, 2.0)  # a 2 mm plate, closed
    plate = CadSurface(box)
    under = np.c_[rng.uniform(0, 400, 4000), rng.uniform(0, 300, 4000), np.zeros(4000)]  # its bottom face only
    cpb = plate.closest(under)
    seen = render_view(plate, MapPoints(under, cpb.signed_mm, cpb.normals), View("top", (0.0, 0.0, -1.0),
                                                                                 (0.0, 1.0, 0.0)), norm, 200)
    assert seen.coloured_px == 0


@pytest.mark.slow
def test_the_alignment_covariance_matches_the_scatter_of_repeated_fits():
    """The fit's 6x6 covariance (t mm, r rad about its centre) predicts the scatter of the pose over 30 noise
    draws of the same 3 000 points of the double-curved part (0.05 mm noise) to within a factor 1.5 a component."""
    cfg = AlignmentCriteria.from_section(CFG, alignment_distances_mm=(4.0,))
    part = PARTS["double-curved"]()
    surface = CadSurface(part.mesh)
    rng = np.random.default_rng(8)
    p0, n0 = part.measured(3000, 0.0, rng)
    poses, covs = [], []
    for _ in range(30):
        a = fit_to_surface(surface, p0 + rng.normal(0, 0.05, len(p0))[:, None] * n0, np.eye(4), cfg, "truth",
                           np.eye(4))
        c = np.array(a.covariance_centre_F_mm)
        poses.append(np.r_[F.transform_points(a.T_F_W, c[None])[0] - c, F.to_rotvec(a.T_F_W)[1]])
        covs.append(a.covariance)
    ratio = np.sqrt(np.diag(np.cov(np.array(poses).T)) / np.diag(np.mean(covs, axis=0)))
    assert np.all((ratio > 1 / 1.5) & (ratio < 1.5)), ratio
