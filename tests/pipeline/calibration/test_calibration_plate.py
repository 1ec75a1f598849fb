"""Calibration plate: sphere fits and the plate frame (Eq. 7-8) against exact synthetic scans."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from tandemscan.config import load_config
from tandemscan.config.models import CalibrationConfig
from tandemscan.pipeline.calibration.plate import (
    PlateError,
    fit_plate,
    fit_sphere,
    fit_sphere_algebraic,
    nominal_centres_P,
    plate_frame,
    plate_frame_covariance,
)
from tandemscan.pipeline.calibration.poses import calibration_views
from tandemscan.pipeline.geometry.frames import invert, pose_error, transform_points
from tandemscan.sim_drivers.plate import plate_mesh, scan_plate


@pytest.fixture
def cal(sim_config):
    return sim_config.calibration


def _view(i: int, cfg) -> np.ndarray:
    """True ``T_S_P`` of view i of the calibration job's pattern."""
    return invert(calibration_views(cfg, load_config().scanner)[i])


def _sphere_points(rng, centre, r, n=400):
    d = rng.normal(size=(n, 3))
    d[:, 2] = -np.abs(d[:, 2])  # the cap facing the scanner at the origin
    return centre + r * d / np.linalg.norm(d, axis=1, keepdims=True)


def test_algebraic_fit_is_exact_on_exact_points():
    rng = np.random.default_rng(0)
    c = np.array([5.0, -3.0, 440.0])
    centre, r = fit_sphere_algebraic(_sphere_points(rng, c, 19.05))
    assert np.linalg.norm(centre - c) < 1e-9 and r == pytest.approx(19.05, abs=1e-9)


def test_ransac_fit_ignores_outliers_the_algebraic_fit_does_not():
    rng = np.random.default_rng(1)
    c = np.array([0.0, 0.0, 450.0])
    pts = _sphere_points(rng, c, 19.05) + rng.normal(0, 0.05, (400, 3))
    outliers = c + rng.uniform(-25, 25, (150, 3))
    outliers[:, 2] = c[2] + rng.uniform(-25, -5, 150)
    P = np.vstack([pts, outliers])
    algebraic, _ = fit_sphere_algebraic(P)
    f = fit_sphere(P, 19.05, noise_mm=0.05, rng=rng)
    assert np.linalg.norm(algebraic - c) > 0.5
    assert np.linalg.norm(f.centre - c) < 0.02
    assert f.n_inliers < len(P) - 100 and abs(f.free_radius_mm - 19.05) < 0.05


@pytest.mark.parametrize("view", [0, 1, 4])
def test_noise_free_plate_gives_centres_within_0_02_mm(cal, sim_config, view):
    T = _view(view, cal)
    pts, _ = scan_plate(cal, sim_config.scanner, T)
    fit = fit_plate(pts, cal, noise_mm=0.001)
    truth = transform_points(T, nominal_centres_P(cal))
    assert np.linalg.norm(fit.centres_S - truth, axis=1).max() < 0.02
    dt, dr = pose_error(fit.T_S_P, T)
    assert dt < 0.02 and np.degrees(dr) < 0.01
    assert max(abs(v) for v in fit.layout_residuals_mm.values()) < 0.02


@pytest.mark.parametrize("seed", [2, 3])
def test_noisy_plate_centres_within_three_sigma(cal, sim_config, seed):
    rng = np.random.default_rng(seed)
    T = _view(seed, cal)
    pts, _ = scan_plate(cal, sim_config.scanner, T, rng=rng, noise_mm=0.05)
    fit = fit_plate(pts, cal, noise_mm=0.05, rng=rng)
    err = np.linalg.norm(fit.centres_S - transform_points(T, nominal_centres_P(cal)), axis=1)
    assert err.max() < 3 * 0.05
    assert err.max() < 0.03  # hundreds of points per sphere: far below the single-point noise
    # noise is along the ray; the radial residual is its projection on the sphere normal
    assert all(0.02 < s.rms_mm < 0.06 for s in fit.spheres.values())
    assert 0 < fit.centre_sigma_mm < 0.02
    assert fit.covariance.shape == (6, 6) and 0 < np.sqrt(fit.covariance[0, 0]) < 0.02


@pytest.mark.parametrize("missing", ["A", "X", "Y"])
def test_missing_sphere_is_named(cal, sim_config, missing):
    pts, _ = scan_plate(cal, sim_config.scanner, _view(0, cal), hidden=(missing,))
    with pytest.raises(PlateError, match=f"sphere {missing} not found"):
        fit_plate(pts, cal, noise_mm=0.01)


def test_spheres_of_the_wrong_diameter_are_rejected(cal, sim_config):
    big = cal.model_copy(update={"sphere_diameter_mm": 39.1})
    pts, _ = scan_plate(big, sim_config.scanner, _view(0, cal))
    with pytest.raises(PlateError, match="0 sphere"):
        fit_plate(pts, cal, noise_mm=0.01)


def test_plate_frame_follows_eq_7_8():
    a, x, y = np.array([1.0, 2.0, 400.0]), np.array([201.0, 2.0, 400.0]), np.array([51.0, 102.0, 410.0])
    T = plate_frame(a, x, y)
    R = T[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(R[:, 0], [1, 0, 0], atol=1e-12)  # x along A->X
    np.testing.assert_allclose(T[:3, 3], [51.0, 2.0, 400.0], atol=1e-12)  # foot of the perpendicular from Y
    np.testing.assert_allclose(R[:, 2], np.cross(R[:, 0], R[:, 1]), atol=1e-12)
    assert transform_points(np.linalg.inv(T), [y])[0][1] > 0  # Y on +y
    with pytest.raises(PlateError, match="line A-X"):
        plate_frame(a, x, (a + x) / 2)


def test_plate_frame_covariance_matches_monte_carlo():
    rng = np.random.default_rng(5)
    C = np.array([[-100.0, 0, 450], [120.0, 0, 450], [0, 90.0, 455]])
    T0 = plate_frame(*C)
    cov = plate_frame_covariance(C, [0.01, 0.01, 0.01])
    samples = []
    for _ in range(2000):
        T = plate_frame(*(C + rng.normal(0, 0.01, C.shape)))
        dR = T[:3, :3] @ T0[:3, :3].T
        samples.append(np.r_[T[:3, 3] - dR @ T0[:3, 3], Rotation.from_matrix(dR).as_rotvec()])
    mc = np.cov(np.array(samples).T)
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), np.sqrt(np.diag(mc)), rtol=0.1)
    # Y is only 90 mm off the A-X line: the tilt about the plate x axis is the least certain rotation
    assert np.sqrt(cov[3, 3]) > np.sqrt(cov[5, 5])


def test_plate_frame_covariance_takes_full_centre_covariances():
    rng = np.random.default_rng(6)
    C = np.array([[-100.0, 0, 450], [120.0, 0, 450], [0, 90.0, 455]])
    T0 = plate_frame(*C)
    L = np.diag([0.012, 0.008, 0.003])  # each centre: poorest across the view, best along it
    cov = plate_frame_covariance(C, [L @ L.T] * 3)
    samples = []
    for _ in range(2000):
        T = plate_frame(*(C + rng.normal(size=C.shape) @ L.T))
        dR = T[:3, :3] @ T0[:3, :3].T
        samples.append(np.r_[T[:3, 3] - dR @ T0[:3, 3], Rotation.from_matrix(dR).as_rotvec()])
    mc = np.cov(np.array(samples).T)
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), np.sqrt(np.diag(mc)), rtol=0.1)
    iso = plate_frame_covariance(C, [0.003] * 3)
    np.testing.assert_allclose(plate_frame_covariance(C, [0.003**2 * np.eye(3)] * 3), iso, rtol=1e-12)
    with pytest.raises(ValueError, match="3 sigmas or 3 3x3"):
        plate_frame_covariance(C, [0.01, 0.01])


def test_sphere_fit_covariance_is_anisotropic_and_right(sim_config):
    # a 60 deg cap seen from the scanner at the origin: the centre is pinned better along the view (z)
    c, r = np.array([10.0, -5.0, 450.0]), 20.0
    errs, covs = [], []
    for seed in range(40):
        rng = np.random.default_rng(seed)
        d = rng.normal(size=(1500, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        P = c + r * d[d[:, 2] < -0.5][:400]
        P += rng.normal(0, 0.05, P.shape)
        f = fit_sphere(P, r, noise_mm=0.05, rng=rng)
        errs.append(f.centre - c)
        covs.append(f.centre_covariance)
    cov = np.mean(covs, axis=0)
    assert cov[2, 2] < 0.5 * min(cov[0, 0], cov[1, 1])
    e = np.array(errs)
    np.testing.assert_allclose(np.sqrt(np.mean(e**2, axis=0)), np.sqrt(np.diag(cov)), rtol=0.35)
    assert f.centre_sigma_mm == pytest.approx(np.sqrt(np.linalg.eigvalsh(f.centre_covariance).max()))


def test_layout_in_config_must_follow_the_frame():
    with pytest.raises(ValueError, match="plate x axis"):
        CalibrationConfig(centre_A_mm=(-100.0, 5.0, 0.0))


def test_plate_mesh_carries_the_spheres(cal):
    mesh = plate_mesh(cal)
    v = np.asarray(mesh.vertices)
    r = cal.sphere_diameter_mm / 2
    for c in nominal_centres_P(cal):
        d = np.linalg.norm(v - c, axis=1)
        assert np.sum(np.abs(d - r) < 1e-6) > 100
