"""Alignment of a measured cloud to CAD without ground truth: AGV stations, robust best fit, RPS spheres and
a start far off, each recovering a known misplacement of points sampled on the default part."""

from __future__ import annotations

import numpy as np
import pytest
from tandemscan.config.models import InspectionConfig, PartConfig, ReferenceSphereConfig, RegionConfig
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.part import train_nose_mesh
from tandemscan.pipeline.inspection.alignment import (
    AlignmentCriteria,
    align,
    align_plan_stations,
    align_stations,
    fit_to_surface,
)
from tandemscan.pipeline.inspection.inspect import CadSurface, InspectionError
from tandemscan.pipeline.planning.plan import Plan

CENTRE_F = np.array([0.0, 0.0, 800.0])  # the default part's centre
SPHERE_R = 19.05


def transform_error(T, T_true, at=CENTRE_F):
    d = F.transform_points(T @ F.invert(T_true), at[None])[0] - at
    return float(np.linalg.norm(d)), float(np.degrees(F.rotation_angle(T @ F.invert(T_true))))


@pytest.fixture(scope="module")
def part():
    return CadSurface(train_nose_mesh(PartConfig()))


def band_points(surface, rng, n=40_000, noise=0.03):
    """Points on the +y side of the default part in the band the default plan scans (frame F), noisy."""
    mesh = surface.mesh
    V, T = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    c = V[T].mean(axis=1)
    tri = np.nonzero((c[:, 1] > 300) & (c[:, 2] > 450) & (c[:, 2] < 1050) & (c[:, 0] > -1200) & (c[:, 0] < 1250))[0]
    pick = rng.choice(tri, n)
    u = rng.uniform(size=(n, 2))
    u = np.where(u.sum(axis=1, keepdims=True) > 1, 1 - u, u)
    a, b, cc = V[T[pick, 0]], V[T[pick, 1]], V[T[pick, 2]]
    p = a + u[:, :1] * (b - a) + u[:, 1:] * (cc - a)
    return p + rng.normal(0, noise, p.shape) * surface.closest(p).normals


def sphere_points(centre, rng, n=500, noise=0.03):
    """The half of a reference sphere facing +y (what the scanner sees)."""
    d = rng.normal(size=(4 * n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = d[d[:, 1] > 0.2][:n]
    return centre + (SPHERE_R + rng.normal(0, noise, len(d)))[:, None] * d


MISPLACED = F.from_rotvec([12.0, -25.0, 18.0], np.radians([0.2, -0.3, 0.4]))  # T_W_F: centimetres, a degree off


def test_stations_give_T_F_W_exactly_from_exact_poses_and_average_drift():
    T_F_W = F.from_rotvec([1500.0, -300.0, 200.0], [0.01, -0.02, 1.2])
    planned = [F.planar_pose(-750.0, 2000.0, 0.0), F.planar_pose(180.0, 1955.0, -0.13),
               F.planar_pose(900.0, 1800.0, -0.4)]
    measured = [F.invert(T_F_W) @ T for T in planned]
    fit = align_stations(planned, measured)
    assert transform_error(fit.T_F_W, T_F_W) < (1e-9, 1e-9)
    assert max(fit.residuals_mm) < 1e-9
    rng = np.random.default_rng(1)
    drift = [F.planar_pose(*rng.normal(0, 20.0, 2), np.radians(rng.normal(0, 0.3))) for _ in planned]
    fit = align_stations(planned, [F.invert(T_F_W) @ T @ D for T, D in zip(planned, drift, strict=True)])
    mm, deg = transform_error(fit.T_F_W, T_F_W)
    assert 1.0 < mm < 60.0 and deg < 1.0  # centimetres: the chassis' drift, averaged
    assert fit.residual_mm > 1.0
    with pytest.raises(InspectionError, match="matching stations"):
        align_stations(planned, measured[:2])


def test_plan_stations_pair_each_scan_with_the_station_before_it():
    plan = Plan.model_validate({"name": "p", "steps": [
        {"kind": "move_measure", "x_mm": 0.0, "y_mm": 2000.0, "heading_rad": 0.0},
        {"kind": "move_arm", "joints_rad": [0, 1, 1, 1, 0, 0]}, {"kind": "scan"}, {"kind": "scan"},
        {"kind": "move_measure", "x_mm": 800.0, "y_mm": 1900.0, "heading_rad": -0.2},
        {"kind": "scan"},
    ]})
    T_F_W = F.from_rotvec([100.0, 50.0, 0.0], [0.0, 0.0, 0.3])
    stations = [F.planar_pose(0.0, 2000.0, 0.0)] * 2 + [F.planar_pose(800.0, 1900.0, -0.2)]
    fit = align_plan_stations(plan, [F.invert(T_F_W) @ T for T in stations])
    assert transform_error(fit.T_F_W, T_F_W) < (1e-9, 1e-9) and len(fit.residuals_mm) == 2
    with pytest.raises(InspectionError, match="3 scans"):
        align_plan_stations(plan, [np.eye(4)] * 2)


def test_best_fit_recovers_a_misplacement_despite_a_bulge(part):
    rng = np.random.default_rng(2)
    p_F = band_points(part, rng)
    bulge = np.linalg.norm(p_F - [0.0, 960.0, 750.0], axis=1) < 60.0  # a 0.4 mm bulge the fit must not follow
    p_F[bulge] += 0.4 * part.closest(p_F[bulge]).normals
    p_W = F.transform_points(MISPLACED, p_F)
    fit = fit_to_surface(part, p_W, np.eye(4), criteria(), "as given")
    mm, deg = transform_error(fit.T_F_W, F.invert(MISPLACED))
    assert mm < 0.01 and deg < 0.001, (mm, deg)
    assert fit.method == "best-fit" and fit.converged and 0.02 < fit.residual_mm < 0.05  # the noise


def test_best_fit_on_datum_regions_only(part):
    rng = np.random.default_rng(3)
    p_F = band_points(part, rng, noise=0.0)
    nose = p_F[:, 0] > 0.0
    p_F[nose] += [0.0, 0.5, 0.0]  # the nose moved: the body alone is the datum
    body_only = criteria(datum_regions=("body",), regions=(
        RegionConfig(name="body", min_mm=(-1e5, -1e5, -1e5), max_mm=(-200.0, 1e5, 1e5)),))
    T_true = F.from_rotvec([0.0, 0.0, 0.0], np.radians([0.0, 0.0, 0.01]))  # the body band alone fixes no x slide
    fit = fit_to_surface(part, F.transform_points(F.invert(T_true), p_F), np.eye(4), body_only, "as given")
    on_body = F.transform_points(fit.T_F_W @ F.invert(T_true), p_F[~nose & (p_F[:, 0] < -300)])
    assert np.abs(part.signed_distance(on_body)).max() < 0.005
    with pytest.raises(InspectionError, match="not among the inspection regions"):
        fit_to_surface(part, p_F, np.eye(4), criteria(datum_regions=("wing",)), "as given")


def criteria(**keys) -> AlignmentCriteria:
    """The alignment criteria of an ``[inspection]`` section with ``keys``."""
    return AlignmentCriteria.from_section(InspectionConfig(**keys))


def rps_config():
    centres = [(-1010.0, 1002.7, 558.7), (-750.0, 1009.2, 960.6), (51.5, 969.0, 558.7), (804.3, 786.7, 559.7)]
    return criteria(alignment="rps", reference_spheres=tuple(
        ReferenceSphereConfig(name=f"S{i}", centre_mm=c) for i, c in enumerate(centres)))


@pytest.mark.slow
def test_rps_uses_the_spheres_alone_and_reports_each_residual(part):
    rng = np.random.default_rng(4)
    cfg = rps_config()
    surface = band_points(part, rng)
    warp = surface[:, 0] > 300.0
    surface[warp] += [0.0, 0.3, 0.0]  # a warped nose: a best fit would split it, RPS must not see it
    spheres = [sphere_points(np.array(s.centre_mm), rng) for s in cfg.reference_spheres]
    p_F = np.vstack([surface, *spheres])
    p_W = F.transform_points(MISPLACED, p_F)
    a = align(part, p_W, cfg, np.eye(4), "as given")
    mm, deg = transform_error(a.T_F_W, F.invert(MISPLACED))
    assert mm < 0.01 and deg < 0.001, (mm, deg)
    assert a.method == "rps" and [s.name for s in a.spheres] == ["S0", "S1", "S2", "S3"]
    assert all(s.residual_mm < 0.01 and abs(s.radius_mm - SPHERE_R) < 0.02 for s in a.spheres)
    assert a.excluded.sum() >= sum(len(s) for s in spheres) and not a.excluded[: len(surface)][~warp].all()
    summary = a.summary()
    assert summary["method"] == "rps" and len(summary["spheres"]) == 4 and summary["residual_mm"] == a.residual_mm
    # two spheres hidden: no RPS, and the error says which are missing
    with pytest.raises(InspectionError, match="needs 3 reference spheres, found 2"):
        align(part, F.transform_points(MISPLACED, np.vstack([surface, *spheres[:2]])), cfg)


def test_best_fit_from_20_deg_and_200_mm_as_given(part):
    rng = np.random.default_rng(5)
    p_F = band_points(part, rng, n=30_000)
    axis = np.array([0.3, 0.4, 0.866]) / np.linalg.norm([0.3, 0.4, 0.866])
    far = F.from_rotvec(np.array([120.0, -140.0, 80.0]) * 200.0 / np.linalg.norm([120.0, -140.0, 80.0]),
                        np.radians(20.0) * axis)
    fit = align(part, F.transform_points(far, p_F), criteria())
    mm, deg = transform_error(fit.T_F_W, F.invert(far))
    assert mm < 0.01 and deg < 0.001, (mm, deg)


def test_no_alignment_keeps_the_given_frame(part):
    a = align(part, np.zeros((10, 3)), criteria(alignment="none"))
    assert a.method == "none" and np.array_equal(a.T_F_W, np.eye(4)) and a.residual_mm == 0.0
