"""The calibration job on the simulated cell: plate views, tracker, hand-eye, calibration file for measure."""

from __future__ import annotations

import json

import numpy as np
from tandemscan.daemon.calibration.calibrate import run_calibration
from tandemscan.daemon.calibration.current import installation_for_job
from tandemscan.daemon.cell.session import CellSession
from tandemscan.daemon.jobs.pose_correction import mount_prior
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.stitching.installation import Installation
from tandemscan.sim_drivers.cell import with_surveyed_mounts


async def test_calibration_job_recovers_the_true_scanner_mount(sim_config, tmp_path):
    cal = sim_config.calibration.model_copy(update={"poses": 5, "scans_per_pose": 2})
    config = sim_config.model_copy(update={"calibration": cal})
    async with CellSession(config) as session:
        run = await run_calibration(session, config, tmp_path / "calibration.json")
    cell = session.cell
    truth = cell.simulation.world.truth.T_T_S
    err_mm, err_rad = F.pose_error(run.installation.T_T_S, truth)
    nominal_mm, _ = F.pose_error(Installation.nominal(config.installation).T_T_S, truth)
    assert nominal_mm > 1.0  # the sim's nominal mount is visibly off
    assert err_mm < 0.2 and np.degrees(err_rad) < 0.02
    assert run.poses_used == 5 and run.hand_eye.point_rms_mm < 0.2
    assert cell.simulation.world.captures >= 2 * 5  # two plate scans averaged at every pose used

    data = json.loads((tmp_path / "calibration.json").read_text())
    assert data["sources"]["T_T_S"].startswith("hand-eye")
    assert data["sources"]["T_V1_C"].startswith("turns") and data["sources"]["T_V2_B"].startswith("turns")
    # mounts: the chassis axis (roll, pitch) is now within hundredths of a degree; the nominal was tenths
    for k in ("T_V1_C", "T_V2_B"):
        calibrated, nominal, truth = (getattr(i, k) for i in (run.installation, Installation.nominal(
            config.installation), cell.simulation.world.truth))
        tilt = [np.degrees(np.arccos(np.clip(T[2, :3] @ truth[2, :3], -1, 1))) for T in (calibrated, nominal)]
        assert tilt[0] < 0.05 < tilt[1]
    assert F.pose_error(run.installation.T_E_S, cell.simulation.world.truth.T_E_S)[0] < 0.2
    job = config.job.model_copy(update={"installation_source": "calibration",
                                        "calibration_file": tmp_path / "calibration.json"})
    used = installation_for_job(config.model_copy(update={"job": job}))
    np.testing.assert_allclose(used.T_T_S, run.installation.T_T_S)

    # the file carries T_T_S's covariance; the job loads it with the mounts and its pose graph takes it as the prior
    cov = np.array(data["T_T_S_covariance"]["matrix"])
    np.testing.assert_allclose(cov, run.hand_eye.covariance)  # translation first, as the hand-eye result gives it
    assert np.sqrt(cov[0, 0]) == run.hand_eye.sigma_trans_mm[0]
    priors = {}
    labels = {"calibration": "calibration file", "nominal": "CAD tolerance"}
    for source, expected in labels.items():
        cfg = config.model_copy(update={"job": job.model_copy(update={"installation_source": source})})
        priors[source], label = mount_prior(cfg, used)
        assert label == expected
    np.testing.assert_allclose(priors["calibration"].covariance, cov)
    assert np.sqrt(priors["nominal"].covariance[0, 0]) == config.correction.mount_nominal_sigma_mm

    # a benchmark's surveyed mounts come as a calibration file: the true mounts, stated far tighter than a
    # calibration's, so that the job's correction keeps them
    surveyed_cfg = with_surveyed_mounts(config, cell.simulation, tmp_path)
    surveyed = installation_for_job(surveyed_cfg)
    for k in ("T_V1_C", "T_V2_B", "T_E_S", "T_T_S"):
        np.testing.assert_array_equal(getattr(surveyed, k), getattr(cell.simulation.world.truth, k))
    survey_prior, label = mount_prior(surveyed_cfg, surveyed)
    assert label == "calibration file" and np.all(np.diag(survey_prior.covariance) < np.diag(cov) * 1e-3)
    off = config.model_copy(update={"correction": config.correction.model_copy(update={"estimate_mount": False})})
    assert mount_prior(off, used) == (None, "off")


async def test_the_calibration_covariance_is_consistent_with_its_error_over_seeds(sim_config, tmp_path):
    """The job's mount prior is the calibration's covariance, so it must be honest: over several sim seeds (each
    its own true mounts and noise) the normalised squared error ``v^T C^-1 v`` of ``T_T_S`` (v in the file's
    order: ``T_T_S -> T_T_S [R(r), t]``) averages the 6 of a chi-square with 6 degrees of freedom. An
    optimistic covariance (1-sigma half the error) would average about 24, a pessimistic one (twice) 1.5."""
    nees = []
    for seed in range(1, 7):
        config = sim_config.model_copy(update={
            "sim": sim_config.sim.model_copy(update={"seed": seed}),
            "calibration": sim_config.calibration.model_copy(update={"poses": 10, "scans_per_pose": 1,
                                                                     "tracker_samples": 5}),
        })
        async with CellSession(config) as session:
            run = await run_calibration(session, config, tmp_path / f"calibration-{seed}.json")
        truth = session.cell.simulation.world.truth.T_T_S
        t, r = F.to_rotvec(F.invert(run.installation.T_T_S) @ truth)
        v = np.r_[t, r]
        cov = np.array(json.loads((tmp_path / f"calibration-{seed}.json").read_text())["T_T_S_covariance"]["matrix"])
        nees.append(float(v @ np.linalg.solve(cov, v)))
    # mean of 6 chi-square(6) draws: 6 +- 1.4; [2.5, 12] holds with probability > 0.99
    assert 2.5 < np.mean(nees) < 12.0, nees
