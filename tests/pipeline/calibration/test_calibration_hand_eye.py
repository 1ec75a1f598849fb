"""Hand-eye calibration A X = X B against synthetic data with a known X."""

from __future__ import annotations

import numpy as np
import pytest
from tandemscan.pipeline.calibration.hand_eye import CLOSED_FORM, METHODS, HandEyeError, solve_hand_eye
from tandemscan.pipeline.calibration.plate import nominal_centres_P, plate_frame, plate_frame_covariance
from tandemscan.pipeline.calibration.poses import plate_view_poses
from tandemscan.pipeline.geometry.frames import from_rotvec, from_rpy, invert, pose_error, transform_points
from tandemscan.pipeline.geometry.uncertainty import skew
from tandemscan.sim_drivers.plate import hand_eye_dataset

X_TRUE = from_rpy([3.0, -88.0, 42.0], np.radians([179.2, 0.4, -0.3]))
T_C_P = from_rpy([400.0, 250.0, 3000.0], np.radians([175.0, 8.0, 20.0]))
VIEWS = plate_view_poses(14, (10.0, 33.0, 0.0), 442.0, 25.0)
PLATE_SIGMA = (0.005, float(np.radians(0.002)))  # (mm, rad) of the synthetic plate poses at scale 1


def _data(sim_config, seed, scale=1.0, views=VIEWS, plate_scale=None):
    """Tracker noise of the config times ``scale``; plate poses with ``PLATE_SIGMA`` times ``plate_scale``
    (default ``scale``)."""
    plate_scale = scale if plate_scale is None else plate_scale
    tracker = sim_config.sim.tracker_noise.model_copy(
        update={k: getattr(sim_config.sim.tracker_noise, k) * scale for k in
                ("position_noise_mm", "position_noise_mm_per_m", "angle_noise_deg", "angle_noise_deg_per_m")}
    )
    return hand_eye_dataset(
        np.random.default_rng(seed), views, X_TRUE, T_C_P, tracker,
        plate_sigma=(PLATE_SIGMA[0] * plate_scale, PLATE_SIGMA[1] * plate_scale),
    )


@pytest.mark.parametrize("method", METHODS)
def test_every_method_is_exact_on_exact_data(sim_config, method):
    d = _data(sim_config, 0, scale=0.0)
    r = solve_hand_eye(d.T_C_T, d.T_S_P, method=method)
    dt, dr = pose_error(r.T_T_S, X_TRUE)
    assert dt < 1e-6 and dr < 1e-7
    assert r.rot_residuals_deg.max() < 1e-6 and r.trans_residuals_mm.max() < 1e-6
    dt, dr = pose_error(r.T_C_P, T_C_P)
    assert dt < 1e-6 and dr < 1e-7
    assert len(r.pairs) == len(r.rot_residuals_deg) and len(r.pairs) + r.rejected_pairs == 14 * 13 // 2


def _plate_covariance(T_S_P: np.ndarray, scale: float) -> np.ndarray:
    """``hand_eye_dataset``'s plate noise (rotation about the plate origin, translation added) in
    ``PlateFit.covariance``'s convention (left perturbation about the S origin): ``dt' = dt + t x dtheta``."""
    J = np.eye(6)
    J[:3, 3:] = skew(T_S_P[:3, 3])
    return J @ np.diag(np.repeat(np.square(PLATE_SIGMA), 3) * scale**2) @ J.T


def _surface_err(T: np.ndarray) -> float:
    dt, dr = pose_error(T, X_TRUE)
    return dt + dr * 442.0


def test_noisy_data_error_is_small_and_within_the_reported_uncertainty(sim_config):
    for seed in range(4):
        d = _data(sim_config, seed)
        r = solve_hand_eye(d.T_C_T, d.T_S_P, tracker_covariances=d.tracker_covariances,
                           plate_covariances=[_plate_covariance(T, 1.0) for T in d.T_S_P])
        dt, dr = pose_error(r.T_T_S, X_TRUE)
        assert dt < 4 * np.linalg.norm(r.sigma_trans_mm) and np.degrees(dr) < 4 * np.linalg.norm(r.sigma_rot_deg)
        assert 0.005 < np.linalg.norm(r.sigma_trans_mm) < 0.2
        assert r.point_rms_mm < 0.1 and len(r.point_residuals_mm) == 14


@pytest.mark.parametrize("scale", [0.5, 1.0, 2.0])
def test_refine_beats_every_closed_form_in_aggregate(sim_config, scale):
    """Maximum likelihood with the right noise model: the smallest surface error at every tracker noise
    level, the plate noise staying as it is (at x0.5 the plate side dominates)."""
    errs = {m: [] for m in METHODS}
    for seed in range(10):
        d = _data(sim_config, 100 + seed, scale, plate_scale=1.0)
        cov = [_plate_covariance(T, 1.0) for T in d.T_S_P]
        for m in METHODS:
            r = solve_hand_eye(d.T_C_T, d.T_S_P, method=m, tracker_covariances=d.tracker_covariances,
                               plate_covariances=cov)
            errs[m].append(_surface_err(r.T_T_S))
    rms = {m: float(np.sqrt(np.mean(np.square(v)))) for m, v in errs.items()}
    assert rms["refine"] <= min(rms[m] for m in CLOSED_FORM), rms
    assert rms["refine"] < 0.08 * max(scale, 1.0)


def _centre_data(sim_config, seed, L):
    """Hand-eye data whose plate poses come from noisy sphere centres (noise ``L @ normal`` in frame S)."""
    rng = np.random.default_rng(seed)
    layout = nominal_centres_P(sim_config.calibration)
    centres = []

    def fit(T_S_P):
        c = transform_points(T_S_P, layout) + rng.normal(size=(3, 3)) @ L.T
        centres.append(c)
        return plate_frame(*c)

    d = hand_eye_dataset(rng, VIEWS, X_TRUE, T_C_P, sim_config.sim.tracker_noise, plate_fit=fit)
    return d, layout, np.array(centres)


def test_refine_on_measured_centres_beats_the_closed_forms(sim_config):
    L = np.diag([0.006, 0.006, 0.003])  # sphere caps: better along the view than across
    errs = {m: [] for m in (*CLOSED_FORM, "refine", "refine_poses")}
    for seed in range(8):
        d, layout, centres = _centre_data(sim_config, 200 + seed, L)
        common = {"plate_points_P": layout, "tracker_covariances": d.tracker_covariances}
        for m in CLOSED_FORM:
            errs[m].append(_surface_err(solve_hand_eye(d.T_C_T, d.T_S_P, method=m, **common).T_T_S))
        r = solve_hand_eye(d.T_C_T, d.T_S_P, plate_points_S=centres,
                           plate_point_covariances=np.broadcast_to(L @ L.T, (14, 3, 3, 3)), **common)
        errs["refine"].append(_surface_err(r.T_T_S))
        cov = [plate_frame_covariance(c, [L @ L.T] * 3) for c in centres]
        r = solve_hand_eye(d.T_C_T, d.T_S_P, plate_covariances=cov, **common)
        errs["refine_poses"].append(_surface_err(r.T_T_S))
    rms = {m: float(np.sqrt(np.mean(np.square(v)))) for m, v in errs.items()}
    best_closed = min(rms[m] for m in CLOSED_FORM)
    assert rms["refine"] <= best_closed and rms["refine_poses"] <= best_closed, rms


def test_measured_centres_exact_data_give_the_exact_answer(sim_config):
    layout = nominal_centres_P(sim_config.calibration)
    d0 = _data(sim_config, 0, scale=0.0)
    c0 = np.array([transform_points(T, layout) for T in d0.T_S_P])
    r = solve_hand_eye(d0.T_C_T, d0.T_S_P, plate_points_P=layout, plate_points_S=c0,
                       plate_point_covariances=np.broadcast_to(1e-6 * np.eye(3), (14, 3, 3, 3)))
    dt, dr = pose_error(r.T_T_S, X_TRUE)
    assert dt < 1e-6 and dr < 1e-7
    assert pose_error(r.T_C_P, T_C_P)[0] < 1e-6


def test_rotations_about_one_axis_are_rejected(sim_config):
    # the scanner turns about its own view axis only: every relative rotation shares that axis
    views = [VIEWS[0] @ from_rotvec([0, 0, 0], [0, 0, a]) for a in np.radians([0, 20, 45, 70, 100])]
    d = _data(sim_config, 1, views=views)
    with pytest.raises(HandEyeError, match="one axis"):
        solve_hand_eye(d.T_C_T, d.T_S_P)


def test_small_relative_rotations_are_dropped_then_rejected(sim_config):
    views = [VIEWS[0] @ from_rotvec([i * 10.0, 0, 0], [0.01 * i, 0.01, 0]) for i in range(5)]
    d = _data(sim_config, 2, views=views)
    with pytest.raises(HandEyeError, match="rotate enough"):
        solve_hand_eye(d.T_C_T, d.T_S_P, min_pair_rotation_deg=5.0)
    # mixing in well-rotated views: the small pairs are counted as dropped, the rest solve
    d = _data(sim_config, 2, views=views[:2] + VIEWS[1:8])
    r = solve_hand_eye(d.T_C_T, d.T_S_P)
    assert r.rejected_pairs >= 1 and len(r.pairs) + r.rejected_pairs == 9 * 8 // 2


def test_bad_input_is_reported(sim_config):
    d = _data(sim_config, 3)
    with pytest.raises(HandEyeError, match="at least 3 poses"):
        solve_hand_eye(d.T_C_T[:2], d.T_S_P[:2])
    with pytest.raises(HandEyeError, match="14 target poses but 13"):
        solve_hand_eye(d.T_C_T, d.T_S_P[:13])
    bad = d.T_S_P.copy()
    bad[4, :3, :3] *= 1.01
    with pytest.raises(HandEyeError, match=r"plate_poses\[4\] is not a rigid"):
        solve_hand_eye(d.T_C_T, bad)
    with pytest.raises(HandEyeError, match=r"tracker_covariances must be \(14, 6, 6\)"):
        solve_hand_eye(d.T_C_T, d.T_S_P, tracker_covariances=np.eye(6))
    with pytest.raises(HandEyeError, match="unknown method"):
        solve_hand_eye(d.T_C_T, d.T_S_P, method="magic")
    pts = np.zeros((14, 4, 3))
    with pytest.raises(HandEyeError, match=r"plate_points_S must be \(14, 4, 3\), got \(14, 3, 3\)"):
        solve_hand_eye(d.T_C_T, d.T_S_P, plate_points_S=pts[:, :3])
    with pytest.raises(HandEyeError, match="go with plate_points_S"):
        solve_hand_eye(d.T_C_T, d.T_S_P, plate_point_covariances=np.zeros((14, 4, 3, 3)))
    with pytest.raises(HandEyeError, match="plate_point_covariances contains NaN"):
        solve_hand_eye(d.T_C_T, d.T_S_P, plate_points_S=pts, plate_point_covariances=np.full((14, 4, 3, 3), np.nan))


def test_plate_covariances_weight_the_refinement(sim_config):
    d = _data(sim_config, 5)
    cov = np.broadcast_to(np.diag([0.005**2] * 3 + [np.radians(0.002) ** 2] * 3), (14, 6, 6))
    r = solve_hand_eye(d.T_C_T, d.T_S_P, plate_covariances=cov, plate_sigma_mm=0.001)
    assert pose_error(r.T_T_S, X_TRUE)[0] < 0.1
    with pytest.raises(HandEyeError, match="plate_covariances must be"):
        solve_hand_eye(d.T_C_T, d.T_S_P, plate_covariances=cov[:3])


def test_uses_the_plate_points_given(sim_config):
    d = _data(sim_config, 4)
    spheres = np.array([[-110.0, 0, 0], [140.0, 0, 0], [0, 100.0, 0]])
    r = solve_hand_eye(d.T_C_T, d.T_S_P, plate_points_P=spheres)
    assert pose_error(r.T_T_S, X_TRUE)[0] < 0.1
    assert pose_error(invert(r.T_C_P) @ T_C_P, np.eye(4))[0] < 0.2
