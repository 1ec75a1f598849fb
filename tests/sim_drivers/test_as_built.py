"""The simulated part as built: deviations applied to the CAD mesh where configured, the world scans that
mesh (and the fixture's spheres), and the scorer's truth of each deviation agrees with the mesh."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from tandemscan.config import load_config
from tandemscan.config.models import CellConfig, PartConfig
from tandemscan.pipeline.geometry.part import train_nose_mesh
from tandemscan.pipeline.inspection.deviation_areas import DeviationArea
from tandemscan.pipeline.inspection.inspect import CadSurface
from tandemscan.sim_drivers.as_built import as_built_mesh, normal_deviation, scanned_part_mesh
from tandemscan.sim_drivers.config import DentConfig, StepConfig, WarpConfig
from tandemscan.sim_drivers.inspection_score import DeviationTruth, score_areas
from tandemscan.sim_drivers.world import SimWorld

DENT = DentConfig(kind="dent", centre_mm=(-350.0, 996.2, 680.0), radius_mm=40.0, depth_mm=0.3)


@pytest.fixture(scope="module")
def cad():
    return CadSurface(train_nose_mesh(PartConfig()))


def surface_height(mesh, xz, y0=2000.0):
    """Where a ray along -y from (x, y0, z) first meets ``mesh`` (its y, mm)."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    rays = np.array([[x, y0, z, 0.0, -1.0, 0.0] for x, z in xz], np.float32)
    return y0 - scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()


def test_dent_step_and_bend_move_the_mesh_as_their_truth_says(cad):
    step = StepConfig(kind="step", min_mm=(300.0, 0.0, 600.0), max_mm=(400.0, 2000.0, 700.0), step_mm=0.2)
    bend = WarpConfig(kind="bend", start_x_mm=-900.0, end_x_mm=-1400.0, amplitude_mm=0.3)
    built = as_built_mesh(cad.mesh, (DENT, step, bend))
    assert len(built.triangles) > len(cad.mesh.triangles)  # split under the dent and the step
    xz = [(-350.0, 680.0), (-350.0 + 25.0, 680.0), (-350.0, 760.0), (350.0, 650.0), (-1450.0, 700.0), (-600.0, 700.0)]
    moved = surface_height(built, xz) - surface_height(cad.mesh, xz)
    # dent centre -0.3; 25 mm out: the bell at rho 0.625 (~-0.09 along a normal close to +y); outside: 0
    bell = 0.15 * (1 + np.cos(np.pi * 25.0 / 40.0))
    np.testing.assert_allclose(moved[:3], [-0.3, -bell, 0.0], atol=0.01)
    assert moved[3] == pytest.approx(0.2, abs=0.02)  # the stepped patch
    assert moved[4] == pytest.approx(0.3, abs=0.005) and moved[5] == pytest.approx(0.0, abs=1e-6)  # bend, none
    for dev, expect in ((DENT, -0.3), (step, 0.2), (bend, 0.3)):
        at = {DENT: [-350.0, 1100.0, 680.0], step: [350.0, 1100.0, 650.0], bend: [-1450.0, 1100.0, 700.0]}[dev]
        _, truth = normal_deviation(dev, cad, np.array([at]))
        assert truth[0] == pytest.approx(expect, abs=0.02)


def test_twist_turns_about_the_length_axis(cad):
    twist = WarpConfig(kind="twist", start_x_mm=0.0, end_x_mm=1000.0, amplitude_mm=0.5, axis_yz_mm=(0.0, 800.0))
    built = as_built_mesh(cad.mesh, (twist,))
    V0, V1 = np.asarray(cad.mesh.vertices), np.asarray(built.vertices)
    far = V0[:, 0] > 1000.0
    r = np.linalg.norm(V0[far][:, 1:] - [0.0, 800.0], axis=1)
    np.testing.assert_allclose(np.linalg.norm(V1[far] - V0[far], axis=1), 0.5e-3 * r, rtol=1e-6, atol=1e-9)
    assert np.allclose(V1[V0[:, 0] < 0.0], V0[V0[:, 0] < 0.0])


def test_the_world_scans_the_as_built_part_and_the_spheres():
    example = load_config("config/as-built-example.toml")
    assert len(example.sim.as_built.deviations) == 4
    config = example.model_copy(update={"sim": example.sim.model_copy(update={"reference_spheres": True})})
    world = SimWorld(config)
    plain = CellConfig()
    n_spheres = len(config.inspection.reference_spheres)
    assert len(world.mesh.triangles) > len(scanned_part_mesh(plain).triangles) + n_spheres * 1000
    sphere = np.array(config.inspection.reference_spheres[0].centre_mm)
    hit = surface_height(world.mesh, [(sphere[0], sphere[2])])[0]
    assert hit == pytest.approx(sphere[1] + 0.5 * config.inspection.reference_sphere_diameter_mm, abs=0.05)
    assert len(SimWorld(plain).mesh.triangles) == len(train_nose_mesh(plain.part).triangles)


def test_score_counts_found_missed_and_false_areas():
    truths = [DeviationTruth(0, "dent", "lower", (0.0, 0.0, 0.0), -0.3, True),
              DeviationTruth(1, "bulge", "upper", (100.0, 0.0, 0.0), 0.4, True),
              DeviationTruth(2, "bend", "upper", (np.nan,) * 3, 0.0, False)]
    areas = (DeviationArea(1, "upper", (103.0, 0.0, 0.0), 500.0, 0.42, 0.2, 500),
             DeviationArea(2, "upper", (0.5, 0.0, 0.0), 80.0, 0.12, 0.11, 80),  # at the dent, but the wrong side
             DeviationArea(3, "lower", (300.0, 0.0, 0.0), 60.0, -0.11, -0.1, 60))
    score = score_areas(truths, areas)
    assert (score["deviations"], score["found"], score["missed"], score["false_regions"]) == (2, 1, 1, 2)
    assert score["centroid_err_mm_max"] == 3.0 and score["extreme_err_mm_max"] == pytest.approx(0.02)
    assert score["false_area_mm2_max"] == 80.0
