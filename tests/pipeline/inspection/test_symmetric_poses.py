"""Near-symmetric parts aligned from any start (docs/inspection-method.md, "Alignment", twin poses): a part symmetric
but for a small feature (a boss, a chamfer on one end, a pad) lands in its own pose whichever way it is given, turned
180 deg about any axis or upside down, and says how many points proved it; where too few points tell the two poses
apart the alignment says the pose is ambiguous and the verdict is indeterminate, never a wrong pose in silence."""

from __future__ import annotations

import numpy as np
import pytest
from tandemscan.config.models import InspectionConfig
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.inspection.alignment import SETTLED_Z, AlignmentCriteria, align
from tandemscan.pipeline.inspection.inspect import CadSurface
from tandemscan.pipeline.inspection.inspection_job import (
    InspectionSettings,
    Measurement,
    ReportOutput,
    align_and_inspect,
)
from tandemscan.pipeline.inspection.report import InspectedPart
from tandemscan.sim_drivers.generated_parts import (
    barrel_shell,
    chamfered_bar,
    near_symmetric,
    random_misplacement,
)
from tandemscan.sim_drivers.inspection_score import alignment_error

CFG = InspectionConfig(reference_spheres=(), regions=(), best_fit=False)
CRITERIA = AlignmentCriteria.from_section(CFG)


def centre_of(mesh) -> np.ndarray:
    v = np.asarray(mesh.vertices)
    return 0.5 * (v.min(axis=0) + v.max(axis=0))


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
