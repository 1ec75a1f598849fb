"""Hand-eye calibration accuracy: our solvers against OpenCV's ``calibrateHandEye`` on the same pose pairs.

Simulated data with the cell's noise levels: per calibration (100 by default) a random true ``T_T_S`` and
plate pose, the calibration job's views (``calibration.poses``), plate poses from exact scans of the plate
with the scanner's 0.05 mm noise fitted by ``fit_plate`` (so ``T_S_P`` carries the real sphere-fit error),
tracker readings with ``TrackerConfig``'s noise scaled by 0.5, 1 and 2. Every method gets the same readings;
the plate scans and the tracker's unit noise draws are shared by the three levels, so the levels differ only
in the tracker noise scale. Our ``refine`` gets the fitted sphere centres with their fit covariances and the
tracker covariances, as the calibration job does; ``refine_poses`` gets only what OpenCV gets (the poses) plus
their covariances. Then (unless ``--no-job``; ``--job-only`` runs just this part) runs the calibration job on
the sim cell and the default measurement job (with its correction and pose graph, including the shared
``T_T_S`` unknown) with nominal, calibrated and true mounts (``truth``: the cell's surveyed mounts as a
calibration file exact to 0.1 um, ``Simulation.write_survey``), and reports each cloud's RMS to the part
(``cloud_rms_mm``), the tracker-only stitch's (``tracker_only_cloud_rms_mm``),
``calibrated_within_10pct_of_truth`` and the job's mount estimate. ``--consistency SEED ...`` runs only the
calibration job per sim seed and puts its ``T_T_S`` error against the covariance it reports (normalised squared
error, mean 6 where honest; per axis in 1-sigma); ``--band`` adds the band job with calibrated and true mounts.

Prints one JSON object on its last line: ``rot_err_deg`` / ``trans_err_mm`` per method (RMS over trials at
the nominal noise), per noise level under ``by_noise`` the same with ``surface_err_mm`` (translation error
plus rotation error times the sweet-spot distance: what a method does to a scanned point), our best and
OpenCV's best by that measure, ``ours_best_le_opencv_best``, the paired win rate of our best over OpenCV's
best and a bootstrap 95 % interval of their ratio; the plate-side uncertainty (``sphere_centre_err_mm``,
the fits' reported ``sphere_centre_sigma_mm`` and ``plate_pose_sigma``), the load average, and the jobs'
figures.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from clean_exit import clean_exit_on_sigterm
from results import publish
from tandemscan.config import load_config
from tandemscan.pipeline.calibration.hand_eye import METHODS, solve_hand_eye
from tandemscan.pipeline.calibration.plate import PlateFit, fit_plate, nominal_centres_P
from tandemscan.pipeline.calibration.poses import calibration_views
from tandemscan.pipeline.geometry.frames import (
    from_rotvec,
    from_rpy,
    invert,
    pose_error,
    to_rotvec,
    transform_points,
)
from tandemscan.pipeline.stitching.installation import Installation
from tandemscan.sim_drivers.plate import hand_eye_dataset, scan_plate

LEVELS = (0.5, 1.0, 2.0)
OURS = (*METHODS, "refine_poses")
OPENCV = {
    "cv_tsai": cv2.CALIB_HAND_EYE_TSAI,
    "cv_park": cv2.CALIB_HAND_EYE_PARK,
    "cv_horaud": cv2.CALIB_HAND_EYE_HORAUD,
    "cv_andreff": cv2.CALIB_HAND_EYE_ANDREFF,
    "cv_daniilidis": cv2.CALIB_HAND_EYE_DANIILIDIS,
}


def opencv_hand_eye(T_C_T: np.ndarray, T_S_P: np.ndarray, method: int) -> np.ndarray | None:
    """OpenCV's solver: gripper = target T, robot base = tracker camera C, camera = scanner S, target = plate P.
    None where OpenCV raises (Andreff's "determinant(R) is null" on some data sets): counted as a failure."""
    try:
        R, t = cv2.calibrateHandEye(
            [T[:3, :3] for T in T_C_T], [T[:3, 3] for T in T_C_T],
            [T[:3, :3] for T in T_S_P], [T[:3, 3] for T in T_S_P],
            method=method,
        )
    except cv2.error:
        return None
    X = np.eye(4)
    X[:3, :3], X[:3, 3] = R, np.ravel(t)
    return X


@dataclass
class PlateStats:
    """Plate-side figures over all fits: centre errors against the truth and the fits' own uncertainty."""

    centre_err_mm: list[float]
    centre_sigma_mm: list[float]
    pose_sigma_mm: list[float]
    pose_sigma_deg: list[float]

    def add(self, fit: PlateFit, truth_S: np.ndarray) -> None:
        self.centre_err_mm.extend(np.linalg.norm(fit.centres_S - truth_S, axis=1))
        self.centre_sigma_mm.extend(np.sqrt(np.trace(fit.centre_covariances, axis1=1, axis2=2) / 3.0))
        var = np.diag(fit.covariance)
        self.pose_sigma_mm.append(float(np.sqrt(var[:3].mean())))
        self.pose_sigma_deg.append(float(np.degrees(np.sqrt(var[3:].mean()))))

    def summary(self) -> dict[str, dict[str, float]]:
        e = np.asarray(self.centre_err_mm)
        return {
            "sphere_centre_err_mm": {"rms": float(np.sqrt(np.mean(e**2))), "max": float(e.max())},
            # reported 1-sigma per axis (RMS over fits); the error above is a 3-D distance, ~sqrt(3) x
            "sphere_centre_sigma_mm": float(np.sqrt(np.mean(np.square(self.centre_sigma_mm)))),
            "plate_pose_sigma": {"trans_mm_per_axis": float(np.median(self.pose_sigma_mm)),
                                 "rot_deg_per_axis": float(np.median(self.pose_sigma_deg))},
        }


def trial(cfg, rng: np.random.Generator, plate: PlateStats) -> dict[float, dict[str, tuple[float, float]]]:
    """One calibration at every noise level on shared scans; {level: {method: (trans err mm, rot err deg)}}."""
    cal, scanner = cfg.calibration, cfg.scanner
    X = cfg.installation.T_T_S.matrix() @ from_rotvec(rng.normal(0, 2.0, 3), rng.normal(0, np.radians(0.3), 3))
    T_C_P = from_rpy(rng.normal([0, 300, 3000], 200), np.radians(rng.normal([180, 0, 0], 10)))
    views = calibration_views(cal, scanner)
    truth_P = nominal_centres_P(cal)
    fits = []
    for T_P_S in views:
        T_S_P_true = invert(T_P_S)
        pts, normals = scan_plate(cal, scanner, T_S_P_true, rng=rng)
        fit = fit_plate(pts, cal, normals_S=normals, noise_mm=scanner.noise_sigma_mm, rng=rng)
        plate.add(fit, transform_points(T_S_P_true, truth_P))
        fits.append(fit)
    T_S_P = np.array([f.T_S_P for f in fits])
    centres = np.array([f.centres_S for f in fits])
    centre_covs = np.array([f.centre_covariances for f in fits])
    plate_covs = np.array([f.covariance for f in fits])
    noise_seed = int(rng.integers(2**31))
    out: dict[float, dict[str, tuple[float, float]]] = {}
    for scale in LEVELS:
        tracker = cfg.sim.tracker_noise.model_copy(update={
            k: getattr(cfg.sim.tracker_noise, k) * scale
            for k in ("position_noise_mm", "position_noise_mm_per_m", "angle_noise_deg", "angle_noise_deg_per_m")
        })
        shared = iter(T_S_P)
        d = hand_eye_dataset(np.random.default_rng(noise_seed), views, X, T_C_P, tracker,
                             plate_fit=lambda _T, fitted=shared: next(fitted))
        common = {"plate_points_P": truth_P, "tracker_covariances": d.tracker_covariances,
                  "min_pair_rotation_deg": cal.min_pair_rotation_deg}
        solved = {m: solve_hand_eye(d.T_C_T, d.T_S_P, method=m, plate_points_S=centres,
                                    plate_point_covariances=centre_covs, **common).T_T_S for m in METHODS}
        solved["refine_poses"] = solve_hand_eye(d.T_C_T, d.T_S_P, plate_covariances=plate_covs, **common).T_T_S
        solved |= {name: opencv_hand_eye(d.T_C_T, d.T_S_P, code) for name, code in OPENCV.items()}
        out[scale] = {}
        for name, X_est in solved.items():
            dt, dr = pose_error(X_est, X) if X_est is not None else (np.inf, np.inf)
            out[scale][name] = (dt, float(np.degrees(dr)))
    return out


def compare(runs: list[dict[str, tuple[float, float]]], lever_mm: float, rng: np.random.Generator) -> dict:
    """Figures of one noise level from the per-trial errors (paired: every method on the same trials)."""
    names = list(runs[0])
    err = {n: np.array([r[n] for r in runs]) for n in names}
    surf_each = {n: e[:, 0] + np.radians(e[:, 1]) * lever_mm for n, e in err.items()}

    def rms(v: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.square(v))))

    surface = {n: rms(v) for n, v in surf_each.items()}  # inf for a method that failed on some trial
    ours = min(OURS, key=lambda n: surface[n])
    cv_best = min(OPENCV, key=lambda n: surface[n])
    a, b = surf_each[ours], surf_each[cv_best]
    idx = rng.integers(0, len(a), (2000, len(a)))
    ratios = np.sqrt(np.mean(a[idx] ** 2, axis=1) / np.mean(b[idx] ** 2, axis=1))
    return {
        "trans_err_mm": {n: rms(e[:, 0]) for n, e in err.items()},
        "rot_err_deg": {n: rms(e[:, 1]) for n, e in err.items()},
        "surface_err_mm": surface,
        "ours_best": ours,
        "opencv_best": cv_best,
        "ours_best_le_opencv_best": bool(surface[ours] <= surface[cv_best]),
        "ours_over_opencv": surface[ours] / surface[cv_best],
        "ours_over_opencv_ci95": [float(np.percentile(ratios, 2.5)), float(np.percentile(ratios, 97.5))],
        "ours_paired_win_rate": float(np.mean(a < b)),
        "failures": {n: int(np.sum(~np.isfinite(v))) for n, v in surf_each.items() if not np.all(np.isfinite(v))},
        "refine_poses_le_opencv_best": bool(surface["refine_poses"] <= surface[cv_best]),
        "refine_poses_paired_win_rate": float(np.mean(surf_each["refine_poses"] < b)),
    }


async def _calibrate_and_measure(cfg, out: Path) -> dict:
    """Sim cell: calibration job, then the default job (tracker stitch, correction and pose graph with the
    shared ``T_T_S`` unknown, as configured) with each installation source. Cloud RMS (mm) of the default
    job and of its tracker-only stitch, and the ``T_T_S`` error (mm, deg, surface mm) the job's mount
    estimate leaves against the truth."""
    from tandemscan.daemon.calibration.calibrate import run_calibration
    from tandemscan.daemon.cell.session import CellSession
    from tandemscan.daemon.jobs.runner import JobRunner
    from tandemscan.daemon.plans import default_plan_path
    from tandemscan.pipeline.planning.plan import Plan

    started = time.monotonic()
    async with CellSession(cfg) as session:
        run = await run_calibration(session, cfg, out / "calibration.json")
    truth_X = session.cell.simulation.world.truth.T_T_S
    survey = session.cell.simulation.write_survey(out / "surveyed_mounts.json")
    lever = cfg.scanner.sweet_spot_mm
    summary = run.hand_eye.summary()
    result = {"calibration_truth_error": run.truth_error,
              "calibration_job_seconds": round(time.monotonic() - started, 1),
              "calibration_sigma": {"trans_mm": summary["sigma_trans_mm"], "rot_deg": summary["sigma_rot_deg"]},
              "cloud_rms_mm": {}, "tracker_only_cloud_rms_mm": {}, "mount_estimate": {}}
    plan = Plan.load(default_plan_path())
    for source in ("nominal", "calibration", "truth"):
        config = _job_config(cfg, source, run.file, survey)
        async with CellSession(config) as session:
            res = await JobRunner(session, plan, config, out / source).run()
        correction = res.report["correction"]
        result["cloud_rms_mm"][source] = res.report["ground_truth"]["cloud_rms_mm"]
        tracker_only = correction.get("before", res.report["ground_truth"])
        result["tracker_only_cloud_rms_mm"][source] = tracker_only["cloud_rms_mm"]
        mount = correction.get("mount", {})
        if mount.get("estimated"):
            used = {"nominal": Installation.nominal(cfg.installation).T_T_S, "truth": truth_X,
                    "calibration": run.installation.T_T_S}[source]
            result["mount_estimate"][source] = {
                "prior": mount["prior"],
                "T_T_S_err_before": _surface(used, truth_X, lever),
                "T_T_S_err_after": _surface(np.array(mount["T_T_S_refined"]), truth_X, lever),
                "sigma_mm": mount["sigma_mm"], "sigma_deg": mount["sigma_deg"],
                "correction_mm": mount["correction_mm"], "correction_deg": mount["correction_deg"],
                "information_ratio": mount["information_ratio"],
                "estimated_directions": mount["estimated_directions"],
            }
        print(f"default job, {source} mounts: cloud RMS {result['cloud_rms_mm'][source]:.4f} mm "
              f"(tracker only {result['tracker_only_cloud_rms_mm'][source]:.4f} mm)", file=sys.stderr)
    rms = result["cloud_rms_mm"]
    result["calibrated_within_10pct_of_truth"] = rms["calibration"] <= 1.1 * rms["truth"]
    result["calibrated_over_truth"] = rms["calibration"] / rms["truth"]
    result["job_seconds"] = round(time.monotonic() - started, 1)
    return result


async def _consistency(cfg, seeds: list[int], out: Path, band: bool) -> dict:
    """The calibration job per sim seed (each its own true mounts and noise): the ``T_T_S`` error against the
    reported covariance, as normalised squared error ``v^T C^-1 v`` (``v`` in the file's order, ``T_T_S ->
    T_T_S [R(r), t]``: chi-square with 6 degrees of freedom where the covariance is honest, mean 6) and per
    axis in 1-sigma; with ``band`` the default band job with the calibrated and with the true mounts (cloud RMS
    after the correction, mm; the job's mount estimate against the truth)."""
    from tandemscan.daemon.calibration.calibrate import run_calibration
    from tandemscan.daemon.cell.session import CellSession
    from tandemscan.daemon.jobs.runner import JobRunner
    from tandemscan.daemon.plans import default_plan_path
    from tandemscan.pipeline.planning.plan import Plan

    runs, lever, plan = [], cfg.scanner.sweet_spot_mm, Plan.load(default_plan_path())
    for seed in seeds:
        config = cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"seed": seed})})
        async with CellSession(config) as session:
            run = await run_calibration(session, config, out / f"calibration-{seed}.json")
        truth = session.cell.simulation.world.truth.T_T_S
        t, r = to_rotvec(invert(run.installation.T_T_S) @ truth)
        v, cov = np.r_[t, r], run.hand_eye.covariance
        fig = {"seed": seed, "nees": float(v @ np.linalg.solve(cov, v)), "z": (v / np.sqrt(np.diag(cov))).tolist(),
               "err": _surface(run.installation.T_T_S, truth, lever)}
        survey = session.cell.simulation.write_survey(out / f"surveyed_mounts-{seed}.json") if band else None
        for source in ("calibration", "truth") if band else ():
            job_config = _job_config(config, source, run.file, survey)
            async with CellSession(job_config) as session:
                res = await JobRunner(session, plan, job_config, out / f"{source}-{seed}").run()
            fig[f"band_cloud_rms_mm_{source}"] = res.report["ground_truth"]["cloud_rms_mm"]
            mount = res.report["correction"].get("mount", {})
            if "T_T_S_refined" in mount:
                fig[f"band_mount_err_after_{source}"] = _surface(np.array(mount["T_T_S_refined"]), truth, lever)
        if band:
            fig["band_calibrated_over_truth"] = fig["band_cloud_rms_mm_calibration"] / fig["band_cloud_rms_mm_truth"]
        runs.append(fig)
        print(json.dumps(_rounded(fig)), file=sys.stderr, flush=True)
    nees = np.array([f["nees"] for f in runs])
    z = np.array([f["z"] for f in runs])
    result = {"seeds": seeds, "runs": runs, "nees_mean": float(nees.mean()), "nees_expected": 6.0,
              "z_rms_per_axis": np.sqrt(np.mean(z**2, axis=0)).tolist(),
              "surface_err_mm_rms": float(np.sqrt(np.mean([f["err"]["surface_mm"] ** 2 for f in runs])))}
    if band:
        result["band_calibrated_over_truth_max"] = max(f["band_calibrated_over_truth"] for f in runs)
    return result


def _job_config(cfg, source: str, calibration_file: Path, survey_file: Path):
    """``cfg`` for a job with the mounts of ``source``: ``nominal``, ``calibration`` (``calibration_file``) or
    ``truth`` (the cell's surveyed mounts, ``survey_file``)."""
    file = survey_file if source == "truth" else calibration_file
    job = cfg.job.model_copy(update={"installation_source": "nominal" if source == "nominal" else "calibration",
                                     "calibration_file": file})
    return cfg.model_copy(update={"job": job})


def _surface(T: np.ndarray, truth: np.ndarray, lever_mm: float) -> dict[str, float]:
    """Error of a ``T_T_S`` against the truth: translation mm, rotation deg, and their effect on a point
    ``lever_mm`` out (surface mm)."""
    mm, rad = pose_error(T, truth)
    return {"mm": mm, "deg": float(np.degrees(rad)), "surface_mm": mm + rad * lever_mm}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=100, help="calibrations per noise level")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--no-job", action="store_true", help="skip the sim calibration and measurement jobs")
    parser.add_argument("--job-only", action="store_true", help="only the sim calibration and measurement jobs")
    parser.add_argument("--consistency", type=int, nargs="+", metavar="SEED",
                        help="only the calibration job per sim seed: its error against its covariance")
    parser.add_argument("--band", action="store_true", help="with --consistency: the band job with calibrated "
                        "and true mounts per seed")
    args = parser.parse_args(argv)
    cfg = load_config()
    rng = np.random.default_rng(args.seed)
    started = time.monotonic()
    load_before = os.getloadavg()[0]
    if args.consistency:
        result = {"benchmark": "calibration_consistency", "poses": cfg.calibration.poses}
        with tempfile.TemporaryDirectory() as tmp:
            result |= asyncio.run(_consistency(cfg, args.consistency, Path(tmp), args.band))
        return _finish("calibration_consistency", result, started, load_before)
    if args.job_only:
        result = {"benchmark": "calibration", "poses": cfg.calibration.poses}
        with tempfile.TemporaryDirectory() as tmp:
            result |= asyncio.run(_calibrate_and_measure(cfg, Path(tmp)))
        return _finish("calibration-job-only", result, started, load_before)
    plate = PlateStats([], [], [], [])
    runs = [trial(cfg, rng, plate) for _ in range(args.trials)]
    by_noise: dict[str, dict] = {}
    for scale in LEVELS:
        level = compare([r[scale] for r in runs], cfg.scanner.sweet_spot_mm, rng)
        by_noise[f"x{scale:g}"] = level
        ours, cv = level["ours_best"], level["opencv_best"]
        print(f"noise x{scale:g}: ours {ours} {level['surface_err_mm'][ours]:.4f} mm, opencv {cv} "
              f"{level['surface_err_mm'][cv]:.4f} mm, paired win rate {level['ours_paired_win_rate']:.2f}",
              file=sys.stderr)
    nominal = by_noise["x1"]
    result = {
        "benchmark": "calibration",
        "trials_per_level": args.trials,
        "poses": cfg.calibration.poses,
        "scanner_noise_mm": cfg.scanner.noise_sigma_mm,
        "trans_err_mm": nominal["trans_err_mm"],
        "rot_err_deg": nominal["rot_err_deg"],
        "by_noise": by_noise,
        "ours_no_worse_than_opencv_best": all(v["ours_best_le_opencv_best"] for v in by_noise.values()),
        **plate.summary(),
    }
    result["hand_eye_seconds"] = round(time.monotonic() - started, 1)
    if not args.no_job:
        with tempfile.TemporaryDirectory() as tmp:
            result |= asyncio.run(_calibrate_and_measure(cfg, Path(tmp)))
    return _finish("calibration-no-job" if args.no_job else "calibration", result, started, load_before)


def _finish(name: str, result: dict, started: float, load_before: float) -> int:
    """Add time and load, publish the figures as ``name`` (``results.publish``)."""
    result["seconds"] = round(time.monotonic() - started, 1)
    result["load_avg_1min"] = [round(load_before, 2), round(os.getloadavg()[0], 2)]
    result["cpus"] = os.cpu_count()
    publish(name, _rounded(result))
    return 0


def _rounded(value: object) -> object:
    """Floats to 4 significant digits, recursively (the JSON line stays readable); inf and NaN to null."""
    if isinstance(value, float):
        return float(f"{value:.4g}") if np.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _rounded(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_rounded(v) for v in value]
    return value


if __name__ == "__main__":
    clean_exit_on_sigterm()
    sys.exit(main())
