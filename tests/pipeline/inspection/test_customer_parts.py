"""Parts a new customer brings (sim_drivers/generated_parts.py, ``CUSTOMER_PARTS``) and their CAD exports: a thin
skin is fitted on its measured side, not its far side; a closed mesh stored as an STL triangle soup and wound
inward is still signed outward; a cloud whose normals do not face its scanner is aligned without them
(docs/inspection-method.md, "Alignment"); a symmetric part says its twin pose fits as well; a part symmetric but
for a small feature (a boss, a chamfer on one end, a pad) lands in its own pose whichever way it is given, turned
180 deg about any axis or upside down, and says how many points proved it; where too few points tell the two poses
apart the alignment says the pose is ambiguous and the verdict is indeterminate, never a wrong pose in silence
("Twin poses")."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from tandemscan.config.models import InspectionConfig
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.part import read_mesh_file
from tandemscan.pipeline.inspection.alignment import SETTLED_Z, AlignmentCriteria, align
from tandemscan.pipeline.inspection.cad_orientation import orient
from tandemscan.pipeline.inspection.inspect import CadSurface, inspect_cloud
from tandemscan.pipeline.inspection.inspection_job import (
    InspectionSettings,
    Measurement,
    ReportOutput,
    align_and_inspect,
    measured_side,
)
from tandemscan.pipeline.inspection.report import InspectedPart
from tandemscan.sim_drivers.generated_parts import (
    CadExport,
    barrel_shell,
    chamfered_bar,
    near_symmetric,
    random_misplacement,
    stiffened_panel,
    twisted_blade,
)
from tandemscan.sim_drivers.inspection_score import alignment_error

from tests.pipeline.inspection.test_alignment_generated import centre_of

CFG = InspectionConfig(reference_spheres=(), regions=(), best_fit=False)
CRITERIA = AlignmentCriteria.from_section(CFG)


def signs_of_defects(part, areas) -> list[str]:
    """Per seeded defect: the side of the areas within 10 mm of it ("none" where there is none)."""
    out = []
    for d in part.defects:
        near = {a.side for a in areas if np.linalg.norm(np.subtract(a.centroid_mm, d.centre_mm)) < 10.0}
        out.append("none" if not near else near.pop() if len(near) == 1 else "both")
    return out


def expected_signs(part) -> list[str]:
    return ["upper" if d.depth_mm > 0 else "lower" for d in part.defects]


@pytest.mark.parametrize("make, T_W_F", [
    # a 4 mm skin given 3 mm low: without the viewing side its top lands on its bottom face (4 mm off, signs turned)
    (stiffened_panel, F.from_rotvec([20.0, -10.0, -3.0], np.radians([1.0, 0.5, 3.0]))),
    # a 60 mm plate given 50 mm low: without it the top lands on the bottom face (60 mm off)
    (near_symmetric, F.from_rotvec([20.0, -10.0, -50.0], np.radians([1.0, 0.5, 3.0]))),
])
def test_a_thin_wall_is_fitted_on_the_side_its_scanner_saw(make, T_W_F):
    part = make()
    surface = CadSurface(part.mesh)
    p_F, n_F = part.measured(6000, 0.01, np.random.default_rng(2))
    p_W, n_W = F.transform_points(T_W_F, p_F), F.rotate_vectors(T_W_F, n_F)
    a = align(surface, p_W, CRITERIA, toward_W=n_W)
    mm, deg = alignment_error(a.T_F_W, F.invert(T_W_F), centre_of(part.mesh))
    assert mm < 0.05 and deg < 0.005, (mm, deg)
    oriented, _ = measured_side(surface, p_W, a.T_F_W, n_W, None)
    res = inspect_cloud(F.transform_points(a.T_F_W, p_W), oriented, CFG)
    assert signs_of_defects(part, res.areas) == expected_signs(part)


def test_unoriented_normals_are_not_trusted():
    """Normals of either sign at random (a cloud whose normals were estimated, not a scanner's): the fit with
    them leaves half the points behind closed faces, so the cloud is aligned without them, as before."""
    part = near_symmetric()
    p_F, n_F = part.measured(4000, 0.01, np.random.default_rng(3))
    T_W_F = F.from_rotvec([30.0, 20.0, 10.0], np.radians([2.0, -1.0, 4.0]))
    n_F = np.where(np.random.default_rng(4).uniform(size=len(n_F))[:, None] < 0.5, -n_F, n_F)
    a = align(CadSurface(part.mesh), F.transform_points(T_W_F, p_F), CRITERIA, toward_W=F.rotate_vectors(T_W_F, n_F))
    mm, deg = alignment_error(a.T_F_W, F.invert(T_W_F), centre_of(part.mesh))
    assert mm < 0.05 and deg < 0.005, (mm, deg)


@pytest.mark.parametrize("suffix", [".stl", ".ply", ".obj"])
def test_a_closed_triangle_soup_wound_inward_is_signed_outward_without_any_measured_side(tmp_path, suffix):
    """An STL stores every triangle's own three vertices: the mesh is closed by its vertices' positions, so its
    volume decides its outside even where the cloud says nothing of its side (an XYZ file: no normals)."""
    part = twisted_blade()
    mesh = read_mesh_file(CadExport(winding="inward", soup=True).write(part, tmp_path / f"blade{suffix}"))
    V, T = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    o = orient(V, T)
    assert o.by == "closed volume" and o.closed.all() and o.reversed.all()
    surface = CadSurface(mesh)
    p_F, _ = part.measured(3000, 0.0, np.random.default_rng(5))
    oriented, note = measured_side(surface, p_F, np.eye(4), None, None)
    assert "winding disagrees with closed volume" in note
    res = inspect_cloud(p_F, oriented, CFG)
    assert signs_of_defects(part, res.areas) == expected_signs(part)


def test_a_symmetric_part_says_its_twin_pose_fits_as_well():
    """With a boss of 0.6 mm radius no point lands on it: the plate is symmetric to the fit. Turned 180 deg it fits
    as well, and the alignment says so (its ``ambiguity``); no point's deviation differs between the two poses, so
    the verdict is not held by it (the deviations are the part's, shown perhaps at their mirror's places).
    (Near-symmetric parts: below.)"""
    part = near_symmetric(boss_mm=0.6)
    p_F, n_F = part.measured(4000, 0.01, np.random.default_rng(7))
    a = align(CadSurface(part.mesh), p_F, CRITERIA, toward_W=n_F)
    assert a.ambiguity.startswith("the pose turned 180 deg about the axis along") and "reference spheres" in a.ambiguity
    assert a.rival.points_for == a.rival.points_against == 0 and not a.rival.unsettles_verdict
    assert "fits as well" not in "; ".join(a.free_directions)


def test_a_stray_triangle_and_a_thousand_bodies_are_oriented_each():
    """A CAD export with a lone triangle left over (its own patch, no neighbour) and an assembly of many closed
    bodies (fasteners), some wound inward: each body is turned outward by its volume, the lone triangle keeps the
    file's winding, and nothing fails (a lone triangle made the winding walk index a sparse matrix by nothing)."""
    rng = np.random.default_rng(8)
    bodies = o3d.geometry.TriangleMesh()
    for i in range(1000):
        bodies += o3d.geometry.TriangleMesh.create_box(5.0, 5.0, 5.0).translate([10.0 * (i % 40), 10.0 * (i // 40), 0])
    V, T = np.asarray(bodies.vertices), np.asarray(bodies.triangles).copy()
    inward = np.repeat(rng.uniform(size=1000) < 0.3, 12)  # a box is 12 triangles
    T[inward] = T[inward][:, ::-1]
    V = np.vstack([V, [[0.0, -50.0, 0.0], [10.0, -50.0, 0.0], [0.0, -40.0, 0.0]]])
    T = np.vstack([T, [len(V) - 3, len(V) - 2, len(V) - 1]])
    o = orient(V, T)
    assert o.patches == 1001 and o.closed[:-1].all() and not o.closed[-1]
    assert np.array_equal(o.reversed[:-1], inward) and not o.reversed[-1]
    assert "1 open patch of the CAD signed by the file's winding" in o.note


@pytest.mark.parametrize("max_deg, max_mm, how", [
    # the skin's fit stops 32 mm and 8 deg off with 73 % of the points on the CAD, and turned over it fits a
    # little better, 178 deg off: a fit under 98 % from a start nobody vouches for is also sought by the features
    (30.0, 300.0, "then the global stage (FPFH + RANSAC against the CAD)"),
    # turned 100 deg and 1 m off, the fit with the normals finds nothing and the one without lands on the skin's
    # far side, 4 mm off: refitted from there with the normals it lands on the measured side
    (180.0, 1000.0, "refitted from its fit without its normals"),
])
def test_a_stringer_panel_from_an_unknown_start_lands_in_its_own_pose(max_deg, max_mm, how):
    part = stiffened_panel()
    rng = np.random.default_rng(0)
    p_F, n_F = part.measured(20_000, 0.01, rng)
    T_W_F = random_misplacement(rng, max_deg, max_mm)
    a = align(CadSurface(part.mesh), F.transform_points(T_W_F, p_F), CRITERIA, toward_W=F.rotate_vectors(T_W_F, n_F))
    mm, deg = alignment_error(a.T_F_W, F.invert(T_W_F), centre_of(part.mesh))
    assert mm < 0.05 and deg < 0.005, (mm, deg)
    assert a.start.endswith(how)


def half_turn(axis, move_mm=(30.0, -20.0, 10.0)) -> np.ndarray:
    """``T_W_F``: 178 deg about ``axis`` (slightly tilted) through the CAD origin, then moved by ``move_mm``."""
    a = np.asarray(axis, float) + np.array([0.02, -0.01, 0.015])
    return F.from_rotvec(np.asarray(move_mm), np.radians(178.0) * a / np.linalg.norm(a))


def aligned(part, points: int, T_W_F: np.ndarray, seed: int = 1):
    """``align`` of the part's measured cloud given at ``T_W_F`` from an unknown start, with the cloud's normals;
    and its error against the truth at the part's centre (mm, deg)."""
    p_F, n_F = part.measured(points, 0.01, np.random.default_rng(seed))
    a = align(CadSurface(part.mesh), F.transform_points(T_W_F, p_F), CRITERIA, toward_W=F.rotate_vectors(T_W_F, n_F))
    return a, alignment_error(a.T_F_W, F.invert(T_W_F), centre_of(part.mesh))


STARTS = {"about z": half_turn([0.0, 0.0, 1.0]), "upside down": half_turn([1.0, 0.0, 0.0]),
          "end over end": half_turn([0.0, 1.0, 0.0]),
          # a start the boss plate landed upside down from, 15 mm low (the lower truncated cost chose it, the boss's
          # points too few to weigh)
          "any": random_misplacement(np.random.default_rng(1), 180.0, 1000.0)}


@pytest.mark.parametrize("make, start", [
    (near_symmetric, "about z"), (near_symmetric, "upside down"), (near_symmetric, "any"),
    (chamfered_bar, "end over end"), (chamfered_bar, "upside down"),
    (barrel_shell, "about z"),
])
def test_a_near_symmetric_part_given_any_way_round_lands_in_its_own_pose(make, start):
    """The plate's 15 mm boss (0.3 % of its surface), the bar's 10 mm chamfer on one end, the barrel's 4 mm pad: the
    best fit turned over about each of the CAD's principal axes is fitted too, and the points that fit one pose and
    not the other prove the true one (beyond SETTLED_Z of a fair coin's count), so it wins and nothing is
    ambiguous."""
    a, (mm, deg) = aligned(make(), 8000, STARTS[start])
    assert mm < 0.1 and deg < 0.01, (mm, deg, a.start)
    assert a.rival is not None and a.rival.turn_deg > 170.0  # its twin was found and ruled out
    assert a.rival.settled and a.rival.z >= SETTLED_Z and a.ambiguity == "", a.rival
    assert a.summary()["rival_pose"]["settled"] and a.summary()["ambiguity"] is None


@pytest.mark.parametrize("start", ["about z", "upside down"])
def test_a_feature_too_small_to_tell_the_poses_apart_is_said_and_the_verdict_is_indeterminate(tmp_path, start):
    """A 5 mm boss on 4000 points: two or three points on it, not enough to prove either pose. The alignment keeps
    the pose those points favour, names the other in ``ambiguity`` with the counts, and since the deviations differ
    between the two the inspection's verdict is indeterminate with that reason first, not a pass or a fail of
    whichever pose came first."""
    part = near_symmetric(boss_mm=5.0)
    p_F, n_F = part.measured(4000, 0.01, np.random.default_rng(1))
    T_W_F = STARTS[start]
    out = align_and_inspect(
        Measurement(F.transform_points(T_W_F, p_F), F.rotate_vectors(T_W_F, n_F)), InspectedPart(CadSurface(part.mesh)),
        InspectionSettings.from_section(CFG.model_copy(update={"views": ("top",), "map_width_px": 120})),
        ReportOutput(tmp_path))
    a = out.data["alignment"]
    assert a["ambiguity"].startswith("the pose turned 180 deg about the axis along") and "reference spheres" in a[
        "ambiguity"]
    rival = a["rival_pose"]
    assert not rival["settled"] and 0 < rival["points_for"] + rival["points_against"] < SETTLED_Z**2
    assert out.result.verdict == "indeterminate"
    assert out.result.judgement.reasons[0].startswith("the cloud's pose on the CAD is ambiguous")
    assert 'id="ambiguity"' in out.html.read_text()
